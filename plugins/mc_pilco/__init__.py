"""MC-PILCO (Amadio et al., IEEE T-RO 2022) as a learner plugin on PILCO's library.

``particles``: the particle estimate of the policy's cost; ``optimise``: Adam with dropout
reduction; ``learner``: the harness learner (entry point ``mc-pilco``).
"""
