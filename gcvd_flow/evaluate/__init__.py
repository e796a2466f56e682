"""Evaluation: ``metrics`` (ATE / RPE / depth errors, pure math), ``run_eval`` (`gcvd-flow
eval`: a RUN_DIR against a ground-truth folder), ``synth`` (rendered clips with exact ground
truth, for `gcvd-flow synth`, the demo and the tests)."""
