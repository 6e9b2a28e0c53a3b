"""The simulator of the paper's model: scenario parameters, physics, association and the batched core.

`scenario` holds every parameter, `physics` one function per equation, `association` the ED-UAV
matching, and `core.BatchCore` composes them into N scenarios stepped at once (docs/model.md).
"""
