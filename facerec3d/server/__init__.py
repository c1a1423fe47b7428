"""The gallery service (`facerec3d serve`): enrol, identify and verify over HTTP.

* `keys`: API keys with scopes (enrol, query, admin), stored as SHA-256 hashes in a JSON file;
* `jobs`: what the worker processes do with an upload (read within limits, preprocess, enrol or prepare);
* `live`: the gallery kept loaded in the workers, updated in place, each change committed before it is
  acknowledged, queries on consistent snapshots;
* `app`: the HTTP API (FastAPI on uvicorn: pip install 'facerec3d[service]'), its limits, work queue,
  metrics and audit log.

Layering: above `gallery` (and `evaluation`), below `cli`. Only `app` needs the service extra.
"""
