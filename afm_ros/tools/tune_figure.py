"""The drive tune's figure (shared by ``afm_report`` and ``afm_study tune``): amplitude and phase
vs drive frequency as measured, the fitted driven-oscillator response and the working point."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from afm_ros.tools.figures import pyplot


def plot_tune(result, path: Path, title: str) -> Path:
    """Write ``path`` (PNG) for a :class:`afm_ros.core.tune.TuneResult` (its points and fit)."""
    plt = pyplot()

    f, a, p = result.frequency, result.amplitude, result.phase_deg
    fine = np.linspace(f.min(), f.max(), 400)
    model = result.model(fine)
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    ax1.plot(f * 1e-3, a * 1e9, "o", ms=3, label="measured (lock-in)")
    ax1.plot(
        fine * 1e-3,
        np.abs(model) * 1e9,
        "-",
        lw=1,
        label=f"fit: f0 = {result.f0:.2f} Hz, Q = {result.q:.3f}",
    )
    ax1.axvline(result.drive_frequency * 1e-3, color="k", ls=":", lw=1, label="working point")
    ax1.set_ylabel("amplitude [nm]")
    ax1.legend(fontsize=8)
    ax2.plot(f * 1e-3, p, "o", ms=3)
    ax2.plot(fine * 1e-3, -np.degrees(np.angle(model)), "-", lw=1)
    ax2.axvline(result.drive_frequency * 1e-3, color="k", ls=":", lw=1)
    ax2.set_ylabel("phase lag [deg]")
    ax2.set_xlabel("drive frequency [kHz]")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
