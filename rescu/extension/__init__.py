"""Stage II (RESCU-II, paper section 4): each stage-I pattern extended with a CNN.

``proposals`` (region proposals around the stage-I instances) -> ``backbone`` (frozen
CNN features of boxes) -> ``stage2`` (per-image heads, training and prediction), with
``finetune`` (optional backbone fine-tuning), ``head`` (the classifier head and the
deterministic torch context both of them use), ``optim`` (Adam without TorchDynamo) and
``merge`` (joining RPs of one object class). Nothing is imported here.
"""
