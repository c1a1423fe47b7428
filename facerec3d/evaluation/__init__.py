"""Evaluation (chapter §8.4): the run end to end (`run.evaluate`), metrics, score files, plots, reports with
provenance, and the comparison of runs. The protocols live with the datasets (`datasets.protocols`)."""
