"""The data a trained GP hands to moment matching: the contract between ``gp`` and ``moments``.

A full GP and a sparse (FITC) GP both reduce, for prediction, to weights on a set of basis
inputs; moment matching (paper eqs. 14-23) only needs those. Shapes: ``E`` outputs, ``n`` basis
points (training inputs for a full GP, pseudo-inputs for FITC), ``d`` input dimensions.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class GPPosterior:
    """Predictive quantities of ``E`` independent SE-ARD GPs sharing their basis inputs.

    For a deterministic test input ``x`` and output ``a``, with ``k_a(x) = [k_a(X_i, x)]_i``::

        mean_a(x) = beta[a] @ k_a(x)
        var_a(x)  = alpha_a^2 - k_a(x) @ inv_k[a] @ k_a(x)      (latent f, no observation noise)

    Attributes:
        inputs: ``(n, d)`` basis inputs X.
        beta: ``(E, n)``; full GP: ``(K_a + sigma_a^2 I)^-1 y_a``.
        inv_k: ``(E, n, n)``; full GP: ``(K_a + sigma_a^2 I)^-1``; FITC: ``K_mm^-1 - (K_mm + K_mn Lambda^-1 K_nm)^-1`` with
            ``Lambda = diag(K_nn - Q_nn) + sigma_a^2 I`` (as in the reference's gp1).
        log_ell: ``(E, d)`` log length-scales.
        log_alpha: ``(E,)`` log signal standard deviations.
        log_sigma: ``(E,)`` log observation-noise standard deviations (not used by prediction of f).
    """

    inputs: torch.Tensor
    beta: torch.Tensor
    inv_k: torch.Tensor
    log_ell: torch.Tensor
    log_alpha: torch.Tensor
    log_sigma: torch.Tensor

    @property
    def num_outputs(self) -> int:
        return int(self.beta.shape[0])

    @property
    def input_dim(self) -> int:
        return int(self.inputs.shape[1])

    def detach(self) -> "GPPosterior":
        """A copy with every tensor detached (model fixed while the policy is optimised)."""
        return GPPosterior(*(t.detach() for t in (self.inputs, self.beta, self.inv_k, self.log_ell, self.log_alpha, self.log_sigma)))

    def to(self, device: torch.device | str) -> "GPPosterior":
        """The posterior on ``device`` (itself if it is there already)."""
        if self.beta.device == torch.device(device):
            return self
        return GPPosterior(*(t.to(device) for t in (self.inputs, self.beta, self.inv_k, self.log_ell, self.log_alpha, self.log_sigma)))
