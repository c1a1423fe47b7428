"""Datasets (chapter §8.4): catalogs of FRGC v2, Bosphorus and manifest datasets (`catalog`), the evaluation
protocols that split them into gallery and probes (`protocols`), the synthetic range scanner (`synthetic`) and
faces made directly in preprocessed form (`frontal`)."""
