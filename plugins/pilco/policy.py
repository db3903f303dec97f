"""PILCO's policy as the harness sees it, and the data PILCO learns from.

* :func:`layout_for`: a task's state layout (sin/cos of its angles, the preset's exclusions);
* :func:`initial_controller`: the reference's initial linear or RBF controller, squashed;
* :class:`PilcoPolicy`: a controller applied to an observation, saved and loaded as plain data
  (:func:`pilco_policy_state`, :func:`pilco_policy_from_state`); :func:`linear_policy` and
  :func:`linear_policy_from_gain` build one by hand (e.g. a reference LQR);
* :func:`transitions`: the GP's training inputs and targets from recorded episodes.

Shared by every learner on PILCO's library (``pilco``, ``pilco-mean``, ``mc-pilco``).
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict
from typing import Any

import numpy as np
import torch

from harness.learner import Policy
from harness.task import Episode, TaskSpec
from plugins.pilco.controllers import LinearController, RBFController, SquashedController, controller_from_state, controller_state
from plugins.pilco.presets import GENERIC, PRESETS, Preset
from plugins.pilco.propagate import StateLayout, act


def layout_for(spec: TaskSpec, preset: Preset) -> StateLayout:
    """The task's state layout: sin/cos for every angle, minus the preset's exclusions."""
    base = StateLayout.with_trig(spec.state_dim, spec.angle_indices)
    model = tuple(i for i in base.model_inputs if i not in preset.model_exclude)
    policy = tuple(i for i in base.policy_inputs if i not in preset.policy_exclude)
    return StateLayout(spec.state_dim, spec.angle_indices, model, policy)


def linked_steps(episode: Episode) -> int:
    """The transitions of ``episode`` the GP is trained on: all, but the last of a terminated episode (it left
    the allowed region, e.g. the unicycle fell), as the reference ``rollout`` drops it."""
    return max(episode.steps - (1 if episode.terminated else 0), 0)


def transitions(episodes: tuple[Episode, ...] | list[Episode], layout: StateLayout) -> tuple[np.ndarray, np.ndarray]:
    """GP training data from recorded (noisy) observations.

    Inputs ``[a(x_t)[model_inputs], u_t]`` ``(n, q + F)``; targets ``x_{t+1} - x_t`` ``(n, D)``.
    The last transition of a terminated episode is dropped (:func:`linked_steps`).
    """
    xs, us, ys = [], [], []
    for ep in episodes:
        steps = linked_steps(ep)
        if steps == 0:
            continue
        xs.append(ep.observations[:steps])
        us.append(ep.actions[:steps])
        ys.append(ep.observations[1 : steps + 1] - ep.observations[:steps])
    x = torch.as_tensor(np.concatenate(xs), dtype=torch.float64)
    with torch.no_grad():
        inputs = layout.augment(x)[:, layout.model_index]
    return np.concatenate([inputs.numpy(), np.concatenate(us)], axis=1), np.concatenate(ys)


class PilcoPolicy:
    """The learned controller applied to an observation: augment, controller, squash -> ``(F,)``.

    Saved as plain data (:meth:`Pilco.policy_state`): the controller's type, parameters and squashing
    (:func:`~plugins.pilco.controllers.controller_state`) and the state layout's indices.
    """

    def __init__(self, controller: torch.nn.Module, layout: StateLayout) -> None:
        self.controller = controller
        self.layout = layout

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return act(observation, self.controller, self.layout)

    @classmethod
    def snapshot(cls, controller: torch.nn.Module, layout: StateLayout) -> PilcoPolicy:
        """A policy acting with a copy of ``controller`` on the CPU, where the system is stepped (the
        controller may live on a GPU); later changes to ``controller`` do not reach it."""
        return cls(copy.deepcopy(controller).cpu(), layout)


def cpu_state_dict(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    """Copies of ``module``'s ``state_dict`` tensors on the CPU (a learner's saved state)."""
    return {k: v.detach().cpu().clone() for k, v in module.state_dict().items()}


def pilco_policy_state(policy: Policy) -> dict[str, Any]:
    """A :class:`PilcoPolicy` as data: the controller (:func:`~plugins.pilco.controllers.controller_state`)
    and the layout's fields (shared by every learner that hands over PILCO's controllers)."""
    if not isinstance(policy, PilcoPolicy):
        raise TypeError(f"a PILCO policy is a PilcoPolicy, not a {type(policy).__name__}")
    return {"controller": controller_state(policy.controller), "layout": asdict(policy.layout)}


def pilco_policy_from_state(state: dict[str, Any], spec: TaskSpec) -> PilcoPolicy:
    """The :class:`PilcoPolicy` of :func:`pilco_policy_state`, checked against the task's dimensions."""
    layout = StateLayout(**state["layout"])
    if layout.state_dim != spec.state_dim:
        raise ValueError(f"a policy for {layout.state_dim} states, the task has {spec.state_dim}")
    controller = controller_from_state(state["controller"])
    if controller.num_controls != spec.action_dim:
        raise ValueError(f"a policy with {controller.num_controls} controls, the task has {spec.action_dim}")
    return PilcoPolicy(controller, layout)


def linear_policy(spec: TaskSpec, W: np.ndarray, b: np.ndarray, squash: str = "trapezoid") -> PilcoPolicy:
    """PILCO's squashed linear controller ``u = u_max squash(W a + b)`` on the task's policy inputs
    ``a`` (its preset's layout); ``W (F, p)``, ``b (F,)``."""
    u_max = np.asarray(spec.action_high, dtype=np.float64)
    W, b = (torch.from_numpy(np.array(v, dtype=np.float64)) for v in (W, b))
    return PilcoPolicy(SquashedController(LinearController(W, b), u_max, squash), layout_for(spec, PRESETS.get(spec.name, GENERIC)))


def linear_policy_from_gain(spec: TaskSpec, K: np.ndarray, x_star: np.ndarray, squash: str = "trapezoid") -> PilcoPolicy:
    """PILCO's squashed linear controller equal to ``u = -K (x - x*)`` to first order at ``x*``.

    ``K (F, D)``, ``x* (D,)`` in the task's state coordinates; pre-squash ``W = -K / (s u_max)``,
    ``b = -W x*`` with ``s`` the squashing's slope at 0 (:data:`~plugins.pilco.trig.SQUASH_SLOPE`).
    For tasks whose policy sees the raw state (no sin/cos entries), e.g. a reference LQR on the unicycle.
    """
    from plugins.pilco.trig import SQUASH_SLOPE

    layout = layout_for(spec, PRESETS.get(spec.name, GENERIC))
    if layout.policy_inputs != tuple(range(spec.state_dim)):
        raise ValueError(f"{spec.name}: the policy does not see the raw state ({layout.policy_inputs}); a gain on it cannot be mapped")
    u_max = np.asarray(spec.action_high, dtype=np.float64)
    W = -np.asarray(K, dtype=np.float64) / (SQUASH_SLOPE[squash] * u_max[:, None])
    return linear_policy(spec, W, -W @ np.asarray(x_star, dtype=np.float64), squash)


def _initial_policy_input_moments(spec: TaskSpec, layout: StateLayout) -> tuple[torch.Tensor, torch.Tensor]:
    """Moments of the policy inputs under N(mu0, Sigma0) (for placing the RBF centres)."""
    from plugins.pilco.trig import augment_trig

    m = torch.as_tensor(spec.init_mean, dtype=torch.float64)
    S = torch.as_tensor(spec.init_cov, dtype=torch.float64)
    ma, sa = augment_trig(m, S, layout.angle_map)
    idx = layout.policy_index
    return ma[idx], sa[idx[:, None], idx[None, :]]


def initial_controller(spec: TaskSpec, preset: Preset, layout: StateLayout, squash: str | None,
                       generator: torch.Generator, spread: float | None = None,
                       target_scale: float | None = None) -> SquashedController:
    """The reference's initial policy: a linear controller with small random weights, or an RBF
    network with ``preset.num_centres`` centres drawn from the initial policy-input distribution;
    squashed to the task's symmetric control bounds (``squash``: trapezoid, sin or None).

    ``spread`` (RBF only): the centres are instead the policy inputs of states drawn uniformly from
    ``[-spread, spread]`` in every non-angle entry and over the whole circle in every angle
    (:func:`spread_centres`); targets and length-scales as the reference's, unless ``target_scale``
    (spread centres only) draws the targets uniform in ``[-target_scale, target_scale]`` (MC-PILCO's
    random initial weights, in units of the squashing's argument).
    """
    if not np.allclose(spec.action_low, -spec.action_high):
        raise ValueError(f"PILCO's squashing needs symmetric control bounds; {spec.name} has {spec.action_low}..{spec.action_high}")
    p, f = len(layout.policy_inputs), spec.action_dim
    if preset.controller == "linear":
        base = LinearController.initial(p, f, scale=0.01, generator=generator)
    elif spread is None:
        mean, cov = _initial_policy_input_moments(spec, layout)
        base = RBFController.initial(mean, cov, preset.num_centres, f, _initial_length_scales(layout), generator=generator)
    else:
        centres = spread_centres(layout, preset.num_centres, spread, generator)
        base = RBFController.at_centres(centres, f, _initial_length_scales(layout), generator, target_scale)
    return SquashedController(base, spec.action_high, squash)


def perturbed_state(controller: torch.nn.Module, scale: float, generator: torch.Generator) -> dict[str, torch.Tensor]:
    """``controller``'s parameters with every tensor moved by ``scale`` times its own spread (the standard deviation
    over its entries; its magnitude where it has one entry) times standard normal noise drawn from ``generator`` (on
    the host, then moved to the tensor's device): a restart near a policy, not from scratch. Returns a state dict
    (the buffers unchanged); ``controller`` is left as it is."""
    state = {k: v.detach().clone() for k, v in controller.state_dict().items()}
    for name, q in controller.named_parameters():
        q = q.detach()
        spread = q.abs().max() if q.numel() == 1 else q.std()
        state[name] = q + scale * spread * torch.randn(q.shape, generator=generator, dtype=q.dtype).to(q.device)
    return state


def spread_centres(layout: StateLayout, num_centres: int, spread: float, generator: torch.Generator) -> torch.Tensor:
    """``(num_centres, p)`` RBF centres spread over the state space (MC-PILCO's initialisation, Amadio et
    al. 2022): the policy inputs ``a(x)[policy_inputs]`` of states ``x`` uniform in ``[-spread, spread]``
    in each non-angle entry and in ``[-pi, pi]`` in each angle (so sin/cos pairs lie on the circle).

    The reference draws the centres from the initial state distribution instead; where that is narrow
    (cart-pole: std 0.1) they nearly coincide, the policy's Gram matrix is close to singular
    (weights ``beta`` in the thousands) and a small step of the centres changes the policy a lot,
    which moment matching's smoothing tolerates but a particle estimate of J does not
    (``results/benchmarks/particle_gradient_check.md``)."""
    if not spread > 0.0:
        raise ValueError(f"spread must be positive, got {spread}")
    d = layout.state_dim
    half = torch.full((d,), float(spread), dtype=torch.float64)
    if layout.angle_indices:
        half[list(layout.angle_indices)] = math.pi
    x = (2.0 * torch.rand(num_centres, d, generator=generator, dtype=torch.float64) - 1.0) * half
    return layout.augment(x)[:, layout.policy_index]


def _initial_length_scales(layout: StateLayout) -> torch.Tensor:
    """Reference initial policy length-scales: 1 for plain states, 0.7 for sin/cos entries."""
    return torch.tensor([0.7 if i >= layout.state_dim else 1.0 for i in layout.policy_inputs], dtype=torch.float64)
