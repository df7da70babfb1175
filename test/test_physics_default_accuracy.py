"""The default step count is accurate: amplitude within 0.02 nm and phase within 0.05 deg of a
converged run for every z_base from 80 nm down to 5 nm (seed cantilever and DMT sample).

Converged run: steps per period doubled from 4x the default until amplitude changes by less than
1e-4 nm AND phase by less than 1e-3 deg between successive doublings (RK4 convergence is irregular
near contact - the DMT force has a derivative jump at a0 and a (a0-d)^1.5 term - so a single small
amplitude change could be a coincidence; requiring the phase too guards against that).

Steady-state detection: successive 8-period windows agree to 1e-15 m in amplitude and 1e-6 deg in
phase. The transient shrinks by >= e^-1 per 8-period window (decay time Q/pi periods at Q = 25),
so the remaining transient is below ~0.6x the last change: < 1e-6 nm and < 1e-6 deg, negligible
against the 0.02 nm / 0.05 deg targets and the 1e-4 nm convergence criterion.

The default lives in CANTILEVER_SPECS["steps_per_period"]. A dense scan (0.1 nm grid, 5..62 nm,
see docs/study.md) found that 200 steps per period misses the amplitude target (0.022 nm at
z_base 46.6 nm) and that 220 meets both (worst 0.0167 nm at 45.7 nm, 0.0425 deg at 33.9 nm), so
the default is 220. Besides every 5 nm, the z_base list holds the worst points of that scan.
"""

from afm_ros.core.physics import CANTILEVER_SPECS, seed_simulation, steady_state

DEFAULT = CANTILEVER_SPECS["steps_per_period"].default
AMPLITUDE_TARGET = 0.02e-9  # m
PHASE_TARGET = 0.05  # deg
STEADY = dict(amplitude_tol=1e-15, phase_tol_deg=1e-6)

Z_BASES_NM = sorted({*range(80, 4, -5), 62, 58, 57, 52, 46.6, 45.7, 43.9, 43.1, 38.6, 36.9, 36.1, 33.9, 27.6,
                     24.2, 12, 7}, reverse=True)


def steady_amp_phase(z_base, spp):
    result = steady_state(seed_simulation(z_base, spp), **STEADY)
    assert result.converged
    return result.analysis.amplitude, result.analysis.phase_deg


def converged(z_base):
    spp = 4 * DEFAULT
    prev = steady_amp_phase(z_base, spp)
    while spp < 32 * 4 * DEFAULT:
        spp *= 2
        cur = steady_amp_phase(z_base, spp)
        if abs(cur[0] - prev[0]) < 1e-4 * 1e-9 and abs(cur[1] - prev[1]) < 1e-3:
            return cur, spp
        prev = cur
    raise AssertionError(f"no converged reference at z_base={z_base:g} m up to spp={spp}")


def test_default_step_count_is_accurate_from_80_to_5_nm():
    rows = []
    for zb_nm in Z_BASES_NM:
        zb = zb_nm * 1e-9
        (a_ref, p_ref), spp_ref = converged(zb)
        a, p = steady_amp_phase(zb, DEFAULT)
        rows.append((zb_nm, (a - a_ref) * 1e9, p - p_ref, spp_ref))
    table = "\n".join(f"z_base {z:5.1f} nm: dA {da:+.4f} nm, dphase {dp:+.4f} deg (ref spp {s})"
                      for z, da, dp, s in rows)
    bad = [r for r in rows if abs(r[1]) * 1e-9 >= AMPLITUDE_TARGET or abs(r[2]) >= PHASE_TARGET]
    assert not bad, f"default steps_per_period={DEFAULT} misses the target:\n{table}"
    # the test is sensitive: near contact the default's error is a visible fraction of the target
    assert max(abs(r[1]) for r in rows) > 0.002
