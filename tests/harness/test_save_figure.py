"""harness.learner_logs.save_figure: per-trial plots as palette PNGs, smaller and looking the same."""

from __future__ import annotations

import numpy as np

from harness.learner_logs import save_figure


def _prediction_like_figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.linspace(0, 4, 40)
    mean, std = 1 - np.exp(-t) * np.cos(3 * t) * 0.5, 0.05 + 0.1 * t
    fig, ax = plt.subplots(figsize=(6, 3.2), dpi=110)
    ax.fill_between(t, mean - 2 * std, mean + 2 * std, color="tab:blue", alpha=0.25, label="predicted ±2σ")
    ax.plot(t, mean, color="tab:blue", label="predicted E[cost]")
    ax.plot(t, mean + 0.05 * np.sin(7 * t), "o-", color="tab:red", ms=3, label="realised")
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    return fig, plt


def test_a_saved_figure_is_a_palette_png_that_looks_like_matplotlibs_own(tmp_path):
    from PIL import Image

    fig, plt = _prediction_like_figure()
    fig.savefig(tmp_path / "rgba.png")
    written = save_figure(fig, tmp_path / "palette.png")
    plt.close(fig)
    assert written == tmp_path / "palette.png"
    with Image.open(tmp_path / "rgba.png") as a, Image.open(written) as b:
        assert b.mode == "P" and a.size == b.size
        reference = np.asarray(a.convert("RGB"), dtype=float)
        quantised = np.asarray(b.convert("RGB"), dtype=float)
    difference = np.abs(reference - quantised)
    assert difference.mean() < 0.5  # levels of 255, over all pixels and channels
    assert np.mean(difference.max(axis=-1) > 16) < 0.01  # under 1 % of pixels visibly off
    assert written.stat().st_size < 0.6 * (tmp_path / "rgba.png").stat().st_size
