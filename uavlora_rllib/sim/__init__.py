"""The simulator of the paper's model: scenario parameters, physics, and the batched core.

`scenario` holds every parameter and `physics` one function per equation (docs/model.md). The
stages of a step, each in its module: `mobility` (Gauss-Markov ED motion and its random stream),
`links` (channel, association via `association`, each served ED's row), `observation` (local
observations, global state), `actions` (action spaces, checks, decoding) and `scoring` (slot
metrics and reward). `core.BatchCore` composes them into N scenarios stepped at once.
"""
