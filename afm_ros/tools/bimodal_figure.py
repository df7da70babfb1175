"""The bimodal frame's figure (``bimodal.png``): height, mode 2's contrast (df2 in AM-FM, its phase
in AM-AM), the recovered and the true modulus, side by side; drawn by ``afm_instrument --bimodal``
and by ``afm_report`` from a recording of the bimodal node."""

from __future__ import annotations

from pathlib import Path

from afm_ros.tools.figures import pyplot


def plot_bimodal(channels: dict, origin: tuple, size: float, fm: bool, path: Path) -> Path:
    """Four panels of ``channels`` (name -> lines x pixels, SI units) over the frame from
    ``origin`` [m] of side ``size`` [m]; ``fm``: mode 2 phase-locked (df2 shown), else its
    phase."""
    plt = pyplot()
    x0, y0 = origin
    rows, cols = channels["height"].shape
    extent = [x0 * 1e6, (x0 + size) * 1e6, (y0 + size * rows / cols) * 1e6, y0 * 1e6]
    fig, axes = plt.subplots(1, 4, figsize=(14, 3.4))
    panels = (
        ("height", 1e9, "height [nm]"),
        ("frequency_shift_2", 1.0, "df2 [Hz]") if fm else ("phase_2", 1.0, "phase 2 [deg]"),
        ("modulus", 1e-9, "E* recovered [GPa]"),
        ("true_modulus", 1e-9, "E* true [GPa]"),
    )
    for ax, (name, scale, label) in zip(axes, panels):
        im = ax.imshow(channels[name] * scale, extent=extent)
        ax.set_title(label)
        ax.set_xlabel("x [um]")
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return Path(path)
