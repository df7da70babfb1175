"""The z spectroscopy figure (``afm_report``'s ``spectroscopy.png``): amplitude and phase vs z gap
on the approach and retract legs, and the mean tip-sample force vs the applied z gap per chunk."""

from __future__ import annotations

from pathlib import Path

from afm_ros.tools.figures import pyplot


def plot_spectroscopy(curve, path: Path, title: str) -> Path:
    """Write ``path`` (PNG) for a :class:`afm_ros.core.spectroscopy.SpectroscopyCurve`."""
    plt = pyplot()

    fig, (ax1, ax2, ax3) = plt.subplots(3, 1, figsize=(7, 8.5), sharex=True)
    for leg, color in (("approach", "tab:blue"), ("retract", "tab:red")):
        m = curve.branch(leg)
        ax1.plot(curve.z_gap[m] * 1e9, curve.amplitude[m] * 1e9, "-", color=color, lw=1, label=leg)
        ax2.plot(curve.z_gap[m] * 1e9, curve.phase[m], "-", color=color, lw=1)
        c = curve.chunk_branch(leg)
        ax3.plot(
            curve.chunk_z_gap[c] * 1e9,
            curve.chunk_force[c] * 1e9,
            ".",
            ms=3,
            color=color,
            label=f"<F_ts> {leg}",
        )
        ax3.plot(
            curve.chunk_z_gap[c] * 1e9,
            curve.spring_constant * curve.chunk_deflection[c] * 1e9,
            "-",
            lw=0.8,
            color=color,
            alpha=0.6,
            label=f"k <deflection> {leg}",
        )
    ax1.axhline(curve.setpoint * 1e9, color="k", ls=":", lw=1, label="setpoint")
    ax1.axvline(
        (curve.z_offset + curve.z_held) * 1e9, color="0.5", ls="--", lw=1, label="held (engaged)"
    )
    ax1.set_ylabel("amplitude [nm]")
    ax1.legend(fontsize=8)
    ax2.set_ylabel("phase lag [deg]")
    ax3.set_ylabel("mean force [nN]")
    ax3.set_xlabel("z gap = z_base + motor + z piezo [nm] (commanded; chunks: applied)")
    ax3.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
