"""State-distribution propagation through the policy and the GP dynamics (reference ``propagate.m``).

One step maps ``p(x_t) = N(m, S)`` (``x (D,)``) to a Gaussian ``p(x_{t+1})``:

1. augment: ``a = [x, sin(x_angles), cos(x_angles)]`` (``D + 2K``), moments by :mod:`trig`;
2. policy: ``u = pi(a[policy_inputs])``; its mean, covariance and ``cov[a, u] = S_a[:, pol] C_u``;
3. dynamics: ``Delta = f([a[model_inputs], u])`` by moment matching (:mod:`moments`) with
   ``cov[x, Delta] = cov[x, inputs] C_Delta``;
4. ``m' = m + M_Delta``, ``S' = S + V_Delta + cov[x, Delta] + cov[x, Delta]^T`` (symmetrised).

Every dimension of ``x`` is predicted as a difference (the GP has ``E = D`` outputs). The
cross-covariances chain in the package convention ``cov[x, g(x)] = S @ C`` (see :mod:`moments`),
which is exact for the jointly Gaussian approximations made at each stage (paper eq. 12).

Gradients: with a fixed dynamics model and a controller whose moment map is a
:class:`~plugins.pilco.controllers.MomentStage`, a whole rollout is one autograd node
(:class:`FusedStep`, :class:`_RolloutFunction`): the stages' hand-derived backward passes are
chained by hand in reverse time order, without per-operator autograd bookkeeping (the policy
objective's J + dJ is dominated by the number of small operator calls). Otherwise (a model with
gradients, a plain callable policy) autograd differentiates :func:`propagate_step_autograd`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
import torch

from plugins.pilco.controllers import MomentMap, MomentStage
from plugins.pilco.kernels import any_failed, deferred_checks, deferred_flags
from plugins.pilco.moments import MomentMatchingGP
from plugins.pilco.posterior import GPPosterior
from plugins.pilco.trig import _doubled, _sin_backward, _sin_forward, augment_trig


@dataclass(frozen=True)
class StateLayout:
    """How a state ``x (D,)`` is presented to the dynamics model and to the policy.

    The augmented state is ``a = [x (D), sin(x[angle_indices]) (K), cos(x[angle_indices]) (K)]``;
    ``model_inputs`` and ``policy_inputs`` index into ``a``. The GP input is
    ``[a[model_inputs], u]``. Cart-pole (``x = [x, xdot, thetadot, theta]``, angle 3):
    ``a = [x, xdot, thetadot, theta, sin theta, cos theta]``, inputs ``(0, 1, 2, 4, 5)``
    (what :meth:`with_trig` builds).
    """

    state_dim: int
    angle_indices: tuple[int, ...]
    model_inputs: tuple[int, ...]
    policy_inputs: tuple[int, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "angle_indices", tuple(int(i) for i in self.angle_indices))
        object.__setattr__(self, "model_inputs", tuple(int(i) for i in self.model_inputs))
        object.__setattr__(self, "policy_inputs", tuple(int(i) for i in self.policy_inputs))
        if any(not 0 <= i < self.state_dim for i in self.angle_indices):
            raise ValueError(f"angle_indices {self.angle_indices} out of range for D = {self.state_dim}")
        for name in ("model_inputs", "policy_inputs"):
            idx = getattr(self, name)
            if not idx or any(not 0 <= i < self.augmented_dim for i in idx) or len(set(idx)) != len(idx):
                raise ValueError(f"{name} {idx} must be distinct indices into the {self.augmented_dim} augmented entries")

    @classmethod
    def with_trig(cls, state_dim: int, angle_indices) -> StateLayout:
        """Model and policy both see the non-angle entries and sin/cos of every angle (not the raw angle)."""
        angles = tuple(int(i) for i in angle_indices)
        k = len(angles)
        inputs = tuple(i for i in range(state_dim) if i not in angles) + tuple(range(state_dim, state_dim + 2 * k))
        return cls(state_dim, angles, inputs, inputs)

    @property
    def num_angles(self) -> int:
        return len(self.angle_indices)

    @property
    def augmented_dim(self) -> int:
        return self.state_dim + 2 * self.num_angles

    @property
    def model_input_dim(self) -> int:
        """GP input dimension excluding the controls."""
        return len(self.model_inputs)

    @cached_property
    def angle_map(self) -> torch.Tensor:
        """``(K, D)`` selector of the angle entries."""
        A = torch.zeros(self.num_angles, self.state_dim, dtype=torch.float64, device="cpu")
        A[torch.arange(self.num_angles, device="cpu"), torch.tensor(self.angle_indices, dtype=torch.long, device="cpu")] = 1.0
        return A

    @cached_property
    def policy_index(self) -> torch.Tensor:
        return torch.tensor(self.policy_inputs, dtype=torch.long, device="cpu")

    @cached_property
    def model_index(self) -> torch.Tensor:
        return torch.tensor(self.model_inputs, dtype=torch.long, device="cpu")

    def on(self, name: str, device: torch.device) -> torch.Tensor:
        """``angle_map``, ``policy_index`` or ``model_index`` on ``device`` (copied once per device)."""
        cache = self.__dict__.setdefault("_on_device", {})
        key = (name, torch.device(device))
        if key not in cache:
            cache[key] = getattr(self, name).to(device)
        return cache[key]

    def policy_noise_cov(self, noise_std) -> torch.Tensor:
        """``(p, p)`` covariance of measurement noise with std ``noise_std (D,)`` on the policy's inputs.

        The policy acts on a noisy observation ``x + eps``, ``eps ~ N(0, diag(noise_std^2))``: its
        input is then ``N(m, S + N)`` while the state stays ``N(m, S)``. Only raw state entries can
        carry it exactly; noise on an angle enters its sin/cos nonlinearly, so a policy that sees
        sin/cos entries is refused.
        """
        std = torch.as_tensor(np.asarray(noise_std, dtype=np.float64))
        if std.shape != (self.state_dim,):
            raise ValueError(f"noise_std has shape {tuple(std.shape)}; the state has {self.state_dim} entries")
        if any(i >= self.state_dim for i in self.policy_inputs):
            raise ValueError("measurement noise on the policy's input needs a policy on raw state entries; this "
                             "layout's policy sees sin/cos of angles")
        return torch.diag(std[self.policy_index] ** 2)

    def augment(self, x: torch.Tensor) -> torch.Tensor:
        """Deterministic ``a(x)`` for ``x (..., D)``."""
        phi = x @ self.on("angle_map", x.device).T
        return torch.cat([x, torch.sin(phi), torch.cos(phi)], dim=-1)


def propagate_step(
    m: torch.Tensor,
    S: torch.Tensor,
    dynamics: MomentMatchingGP,
    policy_moments: MomentMap,
    layout: StateLayout,
    mean_only: bool = False,
    policy_noise: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``N(m, S)`` at time t -> ``(m', S')`` at t+1. ``m (D,)``, ``S (D, D)``.

    ``dynamics`` is ``MomentMatchingGP(posterior)``, ``policy_moments`` is
    ``controller.moment_map()`` (build both once per rollout); ``mean_only`` is passed to
    :meth:`~plugins.pilco.moments.MomentMatchingGP.predict` (deterministic-GP-mean ablation).
    ``policy_noise``: ``(p, p)`` measurement-noise covariance added to the policy's input
    (:meth:`StateLayout.policy_noise_cov`); ``cov[a, u]`` stays ``S_a[:, pol] C_u``, since the
    noise is independent of the state and ``C_u`` is the policy's mean gradient (Stein's lemma).

    With a :class:`~plugins.pilco.controllers.MomentStage` policy and a fixed dynamics model (no
    gradients wrt its posterior) the step is one autograd node with a hand-derived backward pass
    (:class:`FusedStep`); otherwise autograd goes through :func:`propagate_step_autograd`.
    """
    if isinstance(policy_moments, MomentStage) and not dynamics.has_grad:
        return FusedStep(dynamics, policy_moments, layout, mean_only, policy_noise)(m, S)
    return propagate_step_autograd(m, S, dynamics, policy_moments, layout, mean_only, policy_noise)


def propagate_step_autograd(
    m: torch.Tensor,
    S: torch.Tensor,
    dynamics: MomentMatchingGP,
    policy_moments: MomentMap,
    layout: StateLayout,
    mean_only: bool = False,
    policy_noise: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`propagate_step` composed of differentiable pieces, differentiated by autograd
    (the reference for :class:`FusedStep`, and the path for dynamics models with gradients)."""
    d = layout.state_dim
    ma, sa = augment_trig(m, S, layout.on("angle_map", m.device))  # (A,), (A, A)
    pol, mod = layout.on("policy_index", m.device), layout.on("model_index", m.device)

    sp = sa[pol[:, None], pol[None, :]]
    mu, su, cu = policy_moments(ma[pol], sp if policy_noise is None else sp + policy_noise)
    s_au = sa[:, pol] @ cu  # (A, F) cov[a, u]

    s_a_mod = sa[:, mod]  # (A, q) cov[a, a_mod]
    s_mod_u = s_au[mod]  # (q, F)
    m_in = torch.cat([ma[mod], mu])
    s_in = torch.cat(
        [torch.cat([s_a_mod[mod], s_mod_u], dim=1), torch.cat([s_mod_u.T, su], dim=1)], dim=0
    )
    md, vd, cd = dynamics.predict(m_in, s_in, mean_only=mean_only)
    s_x_in = torch.cat([s_a_mod[:d], s_au[:d]], dim=1)  # (D, q + F) cov[x, GP input]
    s_xd = s_x_in @ cd  # (D, D) cov[x, Delta]
    s_next = S + vd + s_xd + s_xd.T
    return m + md, 0.5 * (s_next + s_next.T)


class FusedStep:
    """One time step (:func:`propagate_step`) as a forward/backward pair; a rollout of them is one
    autograd node (:meth:`rollout`).

    The stages and their intermediates, for ``A = D + 2K`` augmented entries, ``p`` policy inputs,
    ``F`` controls and ``q`` model inputs (selections are exact 0/1 matrices)::

        trig:     (mt, vt, ct) = moments of [sin, cos](angles)       (2K,), (2K, 2K), (D, 2K)
        augment:  ma = [m, mt],  sa = [[S, S ct], [ct^T S, vt]]        (A,), (A, A)
        policy:   mp = P_pol ma,  sa_p = sa P_pol^T,  sp = P_pol sa_p  (p,), (A, p), (p, p)
                  (mu, su, cu) = policy(mp, sp [+ N]),  s_au = sa_p cu (F,), (F, F), (p, F), (A, F)
        joint:    mj = [ma, mu],  Sig = [[sa, s_au], [s_au^T, su]]     (A + F,), (A + F, A + F)
        GP input: m_in = P_in mj,  Sig_in = Sig P_in^T,  s_in = P_in Sig_in
        dynamics: (md, vd, cd) = GP moments(m_in, s_in)               (D,), (D, D), (q + F, D)
        update:   s_xd = Sig_in[:D] cd,  m' = m + md,  S' = sym(S + vd + s_xd + s_xd^T)

    The backward pass runs these in reverse with the stages' own backward passes
    (:func:`~plugins.pilco.trig._sin_backward`, :meth:`MomentStage.backward`,
    :meth:`MomentMatchingGP.backward`) and returns gradients wrt ``m``, ``S`` and the policy
    stage's tensors. Numerically it is the same computation as :func:`propagate_step_autograd`.

    ``compile_step``: run each step's forward and backward pass as code made by ``torch.compile``
    (:func:`_compiled`; the same operations, with the elementwise ones fused into fewer kernels: on a
    GPU the step's kernel launches, not its arithmetic, set the time). Made at the first call (tens of
    seconds); the dynamics GP then forms ``Q`` again in the backward pass (as it does by default:
    ``HARNESS_PILCO_KEEP_Q_MB`` is not used). Factorisations inside are checked as
    :func:`~plugins.pilco.kernels.deferred_checks` does; outside such a block a step whose
    factorisation failed is redone without the compiled code, so that it raises (or retries with
    jitter) exactly as without ``compile_step``.
    """

    def __init__(self, dynamics: MomentMatchingGP, policy: MomentStage, layout: StateLayout, mean_only: bool,
                 policy_noise: torch.Tensor | None = None, compile_step: bool = False) -> None:
        self.dynamics, self.policy, self.layout, self.mean_only = dynamics, policy, layout, mean_only
        self.compile_step = bool(compile_step)
        self.policy_noise = policy_noise  # (p, p) or None; a constant: the backward pass is unchanged
        a, f = layout.augmented_dim, dynamics.input_dim - layout.model_input_dim
        device = dynamics.beta.device
        self.p_pol = _selection(layout.policy_inputs, a, device)  # (p, A)
        self.p_in = _selection(layout.model_inputs + tuple(range(a, a + f)), a + f, device)  # (q + F, A + F)
        self.p_pol_t, self.p_in_t = self.p_pol.T.contiguous(), self.p_in.T.contiguous()
        self.trig_maps = _doubled(layout.on("angle_map", device)) if layout.num_angles else None
        self.dyn_needs = (True, True) + (False,) * len(dynamics.constants)

    def __call__(self, m: torch.Tensor, S: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One step: ``(m', S')``."""
        means, covs = self.rollout(m, S, 1)
        return means[1], covs[1]

    def rollout(self, m0: torch.Tensor, S0: torch.Tensor, horizon: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``horizon`` steps from ``N(m0, S0)``: means ``(H+1, D)``, covariances ``(H+1, D, D)``
        (differentiable wrt ``m0``, ``S0`` and the policy: one autograd node, :class:`_RolloutFunction`)."""
        tensors = self.policy.tensors
        if torch.is_grad_enabled() and (m0.requires_grad or S0.requires_grad or any(t.requires_grad for t in tensors)):
            return _RolloutFunction.apply(m0, S0, self, horizon, *tensors)
        with torch.inference_mode():
            means, covs, _ = self.run(m0, S0, horizon, keep=False)
        return means.clone(), covs.clone()  # ordinary tensors for the caller

    def run(self, m0, S0, horizon, keep: bool = True):
        """:meth:`forward` ``horizon`` times: ``(means (H+1, D), covs (H+1, D, D), [saved per step])``.
        ``keep``: the dynamics GP keeps step ``t``'s ``Q`` in its buffer ``t`` for the backward pass."""
        if self.compile_step:  # inference tensors like every later step's (the compiled code is guarded on the kind)
            m0, S0 = m0.clone(), S0.clone()
        means, covs, saved = [m0], [S0], []
        m, S = m0, S0
        for t in range(horizon):
            (m, S), saved_step = self.forward(m, S, slot=t if keep else None)
            means.append(m)
            covs.append(S)
            saved.append(saved_step)
        return torch.stack(means), torch.stack(covs), saved

    def run_backward(self, saved, g_means, g_covs, needs):
        """Gradients wrt ``(m0, S0, *policy.tensors)`` given those wrt the results of :meth:`run`
        (``None`` for zero); the policy tensors' gradients are summed over the steps."""
        S0 = saved[0][0]
        horizon, d = len(saved), S0.shape[0]
        g_means = S0.new_zeros(horizon + 1, d) if g_means is None else g_means
        g_covs = S0.new_zeros(horizon + 1, d, d) if g_covs is None else g_covs
        if self.compile_step:  # see run
            g_means, g_covs = g_means.clone(), g_covs.clone()
        g_m, g_S = g_means[horizon], g_covs[horizon]
        totals = [None] * len(needs)
        for t in reversed(range(horizon)):
            g_m, g_S, *g_policy = self.backward(saved[t], g_m, g_S, needs)
            g_m, g_S = g_m + g_means[t], g_S + g_covs[t]
            totals = [g if total is None else (total if g is None else total + g) for total, g in zip(totals, g_policy)]
        return (g_m, g_S, *totals)

    def forward(self, m, S, slot: int | None = None):
        """``((m', S'), saved)`` without autograd (``slot``: see :meth:`MomentMatchingGP.forward`)."""
        if self.compile_step:
            return _run_compiled("forward", lambda: self._forward(m, S, slot), self, m, S)
        return self._forward(m, S, slot)

    def backward(self, saved, g_m1, g_S1, needs):
        """Gradients wrt ``(m, S, *policy.tensors)`` given those wrt ``(m', S')`` (``needs``: for the tensors)."""
        if self.compile_step:
            return _run_compiled("backward", lambda: self._backward(saved, g_m1, g_S1, needs), self, saved, g_m1, g_S1, needs)
        return self._backward(saved, g_m1, g_S1, needs)

    def _forward(self, m, S, slot: int | None = None):
        """:meth:`forward`'s arithmetic."""
        d = self.layout.state_dim
        if self.trig_maps is None:
            ma, sa, ct, saved_trig = m, S, None, None
        else:
            (mt, vt, ct), saved_trig = _sin_forward(m, S, *self.trig_maps)
            sc = S @ ct  # (D, 2K) cov[x, trig]
            ma = torch.cat([m, mt])
            sa = torch.cat([torch.cat([S, sc], dim=1), torch.cat([sc.T, vt], dim=1)], dim=0)
        a = ma.shape[0]
        sa_p = sa @ self.p_pol_t  # (A, p)
        sp = self.p_pol @ sa_p
        (mu, su, cu), saved_pol = self.policy.forward(self.p_pol @ ma, sp if self.policy_noise is None else sp + self.policy_noise)
        s_au = sa_p @ cu  # (A, F) cov[a, u]
        mj = torch.cat([ma, mu])
        sig = torch.cat([torch.cat([sa, s_au], dim=1), torch.cat([s_au.T, su], dim=1)], dim=0)
        sig_in = sig @ self.p_in_t  # (A + F, q + F)
        (md, vd, cd), saved_dyn = self.dynamics.forward(self.p_in @ mj, self.p_in @ sig_in, self.mean_only, slot)
        x_in = sig_in[:d]  # (D, q + F) cov[x, GP input]
        s_xd = x_in @ cd  # (D, D) cov[x, Delta]
        s_next = S + vd + s_xd + s_xd.T
        saved = (S, ct, saved_trig, sa_p, cu, saved_pol, x_in, cd, saved_dyn, a)
        return (m + md, 0.5 * (s_next + s_next.T)), saved

    def _backward(self, saved, g_m1, g_S1, needs):
        """:meth:`backward`'s arithmetic."""
        S, ct, saved_trig, sa_p, cu, saved_pol, x_in, cd, saved_dyn, a = saved
        d = self.layout.state_dim
        h = 0.5 * (g_S1 + g_S1.T)  # through the symmetrisation
        g_sxd = 2.0 * h  # h + h^T, h symmetric
        g_m_in, g_s_in = self.dynamics.backward(saved_dyn, g_m1, h, x_in.T @ g_sxd, self.mean_only, self.dyn_needs)[:2]
        g_mj = self.p_in_t @ g_m_in  # (A + F,)
        g_sig_in = self.p_in_t @ g_s_in  # (A + F, q + F)
        g_sig_in[:d] += g_sxd @ cd.T
        g_sig = g_sig_in @ self.p_in  # (A + F, A + F)
        g_sau = g_sig[:a, a:] + g_sig[a:, :a].T  # (A, F)
        g_mp, g_sp, *g_policy = self.policy.backward(saved_pol, g_mj[a:], g_sig[a:, a:], sa_p.T @ g_sau, needs)
        g_ma = g_mj[:a] + self.p_pol_t @ g_mp
        g_sa_p = g_sau @ cu.T + self.p_pol_t @ g_sp  # (A, p)
        g_sa = g_sig[:a, :a] + g_sa_p @ self.p_pol  # (A, A)
        g_m = g_m1 + g_ma[:d]
        g_S = h + g_sa[:d, :d]
        if saved_trig is not None:
            g_sc = g_sa[:d, d:] + g_sa[d:, :d].T  # (D, 2K)
            g_m_trig, g_S_trig = _sin_backward(self.trig_maps[0], saved_trig, g_ma[d:], g_sa[d:, d:], S.T @ g_sc)
            g_m = g_m + g_m_trig
            g_S = g_S + g_sc @ ct.T + g_S_trig
        return (g_m, g_S, *g_policy)


def _step_forward(step: FusedStep, m, S):
    return step._forward(m, S)  # no slot: Q is formed again in the backward pass (a kept buffer would be guarded on)


def _step_backward(step: FusedStep, saved, g_m1, g_S1, needs):
    return step._backward(saved, g_m1, g_S1, needs)


#: ``torch.compile``'s backend for ``compile_step`` (environment variable ``HARNESS_PILCO_COMPILE_BACKEND``;
#: the tests trace with ``aot_eager``, which makes no code: inductor's C++ build takes minutes on a small CPU)
COMPILE_BACKEND = os.environ.get("HARNESS_PILCO_COMPILE_BACKEND", "inductor")
_COMPILED: dict[tuple[str, str], object] = {}


def _compiled(name: str):
    """``torch.compile`` of :func:`_step_forward` or :func:`_step_backward`, made at first use (one per
    process and backend: ``torch.compile`` caches the code per guarded input kind, e.g. per GP size)."""
    key = (name, COMPILE_BACKEND)
    fn = _COMPILED.get(key)
    if fn is None:
        fn = _COMPILED[key] = torch.compile({"forward": _step_forward, "backward": _step_backward}[name],
                                            backend=COMPILE_BACKEND)
    return fn


def _run_compiled(name: str, eager, *args):
    """The compiled step pass ``name`` on ``args``, its factorisations' checks collected in a fresh list
    (the same length at every call: the compiled code is guarded on it) and handed on to the caller's
    :func:`~plugins.pilco.kernels.deferred_checks`; outside one, a failed check redoes the pass with
    ``eager()`` (the uncompiled pass, which raises or retries as usual)."""
    outer = deferred_flags()
    with deferred_checks() as flags:
        result = _compiled(name)(*args)
    if outer is not None:
        outer.extend(flags)
        return result
    if flags and bool(any_failed(flags, flags[0])):
        return eager()
    return result


@lru_cache(maxsize=64)
def _selection(indices: tuple[int, ...], size: int, device: torch.device | None = None) -> torch.Tensor:
    """``(len(indices), size)`` 0/1 matrix ``P`` with ``P @ v = v[indices]`` (built once per
    arguments and shared: read it, never write to it; on a GPU a copy from the host per J would be
    a transfer per evaluation that a CUDA graph cannot hold)."""
    P = torch.zeros(len(indices), size, dtype=torch.float64, device="cpu")
    P[torch.arange(len(indices), device="cpu"), torch.tensor(indices, dtype=torch.long, device="cpu")] = 1.0
    return P.to(device) if device is not None else P


class _RolloutFunction(torch.autograd.Function):
    """:meth:`FusedStep.run` and :meth:`FusedStep.run_backward` as one autograd node per rollout.

    Inputs ``(m0, S0, step, horizon, *step.policy.tensors)``; outputs ``means (H+1, D)``,
    ``covs (H+1, D, D)``. Both passes run in ``torch.inference_mode`` (about 15 % less
    per-operator overhead than ``no_grad``); what leaves them is cloned into ordinary tensors.
    """

    @staticmethod
    def forward(ctx, m0, S0, step: FusedStep, horizon: int, *tensors):
        with torch.inference_mode():
            means, covs, saved = step.run(m0, S0, horizon)
        # a plain attribute, not save_for_backward: no outputs are kept, so no reference cycle
        ctx.step, ctx.saved = step, saved
        return means.clone(), covs.clone()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_means, g_covs):
        needs = ctx.needs_input_grad
        with torch.inference_mode():
            grads = ctx.step.run_backward(ctx.saved, g_means, g_covs, needs[4:])
        g_m0, g_S0, *g_tensors = (None if g is None else g.clone() for g in grads)
        return g_m0 if needs[0] else None, g_S0 if needs[1] else None, None, None, *g_tensors


def rollout(
    m0: torch.Tensor,
    S0: torch.Tensor,
    horizon: int,
    posterior: GPPosterior | MomentMatchingGP,
    controller: torch.nn.Module,
    layout: StateLayout,
    mean_only: bool = False,
    policy_noise: torch.Tensor | None = None,
    compile_step: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Predicted state distributions over ``horizon`` steps from ``N(m0, S0)``.

    ``posterior``: the dynamics GP, or a :class:`MomentMatchingGP` of it kept across rollouts (as
    :class:`~plugins.pilco.objective.PolicyObjective` does) to reuse its work buffers.
    ``policy_noise``: ``(p, p)`` measurement noise on the policy's input (:func:`propagate_step`).
    ``compile_step``: the fused rollout's steps as compiled code (:class:`FusedStep`; no effect on the
    autograd path).
    Returns means ``(H+1, D)`` and covariances ``(H+1, D, D)``; index 0 is the initial state.
    """
    dynamics = posterior if isinstance(posterior, MomentMatchingGP) else MomentMatchingGP(posterior)
    posterior = dynamics.posterior
    if posterior.num_outputs != layout.state_dim:
        raise ValueError(f"the dynamics GP has {posterior.num_outputs} outputs; the state has {layout.state_dim}")
    expected = layout.model_input_dim + controller.num_controls
    if posterior.input_dim != expected:
        raise ValueError(f"the dynamics GP takes {posterior.input_dim} inputs; layout + controls give {expected}")
    policy_moments = controller.moment_map()
    if isinstance(policy_moments, MomentStage) and not dynamics.has_grad:
        return FusedStep(dynamics, policy_moments, layout, mean_only, policy_noise, compile_step).rollout(m0, S0, horizon)
    means, covs = [m0], [S0]
    m, S = m0, S0
    for _ in range(horizon):
        m, S = propagate_step_autograd(m, S, dynamics, policy_moments, layout, mean_only, policy_noise)
        means.append(m)
        covs.append(S)
    return torch.stack(means), torch.stack(covs)


def act(x, controller: torch.nn.Module, layout: StateLayout) -> np.ndarray:
    """The policy applied to an observed state ``x (D,)``: augment, controller, squash -> ``u (F,)``."""
    xt = torch.as_tensor(np.asarray(x, dtype=np.float64))
    with torch.no_grad():
        u = controller(layout.augment(xt)[layout.policy_index])
    return u.numpy().copy()
