"""Galleries at scale (chapter §8.6.2: identification costs one match per enrolled face).

* `store`: a persistent gallery in one SQLite file (templates as raw arrays, one transaction per enrolment);
* `engine`: the gallery sharded over executors (in-process, a process per core, or Dask workers), each
  keeping its shard in memory; a probe goes to every shard and the scores are merged;
* `cascade`: a cheap depth-descriptor screen passing a shortlist to full ICP;
* `service`: enrol / identify / verify against a store (the CLI's commands);
* `synthetic`: morphable-model faces made directly in preprocessed form (tests, benchmarks).
"""
