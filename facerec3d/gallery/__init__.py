"""Galleries at scale (chapter §8.6.2: identification costs one match per enrolled face).

* `store`: a persistent gallery in one SQLite file (templates as raw arrays, one transaction per enrolment);
* `engine`: one set of workers (in-process, a process per core, or Dask workers) for a run's reading,
  preprocessing, enrolment and matching, holding the gallery sharded over them, each keeping its shard in
  memory; a probe goes to every shard and the scores are merged;
* `cascade`: a cheap depth-descriptor screen passing a shortlist to full ICP (`Cascade`);
* `service`: enrol / identify / verify against a store (the CLI's commands).
"""
