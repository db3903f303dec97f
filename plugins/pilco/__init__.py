"""PILCO (Deisenroth & Rasmussen, ICML 2011) in PyTorch, float64.

Data flow, one module per step: ``kernels``/``gp`` (dynamics model) -> ``posterior`` (what the
model hands on) -> ``moments`` (GP prediction at uncertain inputs) -> ``propagate`` (state
distributions over the horizon, with the controller) -> ``cost`` (expected saturating cost) ->
``objective`` (J(theta) and its gradient) -> ``learner`` (Algorithm 1 as a harness plugin).
"""
