"""Pipeline tooling around the algorithm: MLflow logging, the Optuna sweep, DVC helpers and the code fingerprint
that lets each task's stages depend on the code of its own family only."""
