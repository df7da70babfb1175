"""The bimodal session's chunk loop compiled: :meth:`BimodalScan.chunk
<afm_ros.core.bimodal_scan.BimodalScan.chunk>` for a run of chunks in one numba call (no ROS).

Per chunk the Python loop costs ~60 us (two ``LockIn.process`` calls, the z and PLL updates, the
drive's retuning, the bookkeeping) against the 25 us the chunk simulates: a live two-mode
instrument cannot run that way. Here every block runs its own arithmetic in the same order on the
same numbers: the two-mode kernel (:func:`~afm_ros.core.physics.modes.advance_two`), the sample
under the tip (:func:`~afm_ros.core.samples.surface.surface_at`), each lock-in's reference anchor
and its demodulator (:func:`~afm_ros.core.lockin.demodulate`), the z controller's and the
oscillation controller's updates, the phase-continuous retuning of mode 2's drive and the pixel
sums, so the frame is the Python loop's bit for bit (test_bimodal_loop, against
``BimodalScan(..., compiled=False)``). Python's ``math.hypot`` (CPython 3.10-3.11: a correctly
rounded sum of squares, Veltkamp splitting) and its ``min``/``max`` are written out for that;
``math.remainder`` by ``fmod``.

The blocks' state goes in and out through small float and integer arrays (:class:`LoopState`),
so a frame may mix compiled runs with Python chunks. The Python blocks stay the reference: this
loop covers the session's use of them (a continuous stream, the z controller enabled without a
slew limit, no lock-in phase offset) and the caller checks that.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from afm_ros.core.lockin import continuity_tolerances, demodulate, lowpass_alpha
from afm_ros.core.physics import modes_events
from afm_ros.core.physics.modes import advance_two
from afm_ros.core.physics.modes_events import advance_two_event
from afm_ros.core.samples.surface import surface_at

TWO_PI = 2.0 * math.pi
T27 = 134217729.0  # 2^27 + 1: Veltkamp's splitting constant for doubles

# float state of a lock-in (LI_*), the z controller (Z_*), the oscillation controller (P_*)
LI_A_TIME, LI_A_PHASE, LI_CPS, LI_A_FREQ, LI_NEXT_K, LI_ALPHA, LI_INTERVAL, LI_RATE = range(8)
LI_HARMONIC = 8
LI_FLOATS = 9
# integer state of a lock-in
LI_HAS_ANCHOR, LI_A_INDEX, LI_NEXT_INDEX, LI_CHUNKS, LI_SAMPLES, LI_JUMPS, LI_ORDER = range(7)
LI_INTS = 7
Z_Z, Z_INTEGRATOR, Z_ERROR, Z_T_LAST, Z_SETPOINT, Z_KP, Z_KI, Z_LO, Z_HI = range(9)
Z_FLOATS = 9
Z_HAS_T, Z_NEEDS_INIT, Z_NON_MONOTONIC = range(3)
(
    P_INTEGRAL, P_DF, P_DRIVE, P_AMP_INTEGRAL, P_PHASE_ERROR, P_AMPLITUDE, P_T_LAST, P_CENTER,
    P_PHASE_SETPOINT, P_PLL_P, P_PLL_I, P_RANGE, P_AMP_SETPOINT, P_AMP_P, P_AMP_I, P_DRIVE_MAX,
) = range(16)  # fmt: skip
P_FLOATS = 16
P_HAS_T, P_PLL_ON, P_AMP_ON = range(3)
# what the scan passes per run: sim steps, deflection samples so far, the z piezo [m]
S_STEPS, S_INDEX = range(2)
# run kinds
ENGAGE, TRACE, RETRACE = range(3)
# error codes
OK, BAD_Z_BASE, BAD_SAMPLES = range(3)


@njit(cache=True, inline="always")
def _min(a, b):
    """Python's min(a, b): b only if b < a."""
    return b if b < a else a


@njit(cache=True, inline="always")
def _max(a, b):
    """Python's max(a, b): b only if b > a."""
    return b if b > a else a


@njit(cache=True)
def py_hypot(a, b):
    """CPython 3.10-3.11's ``math.hypot(a, b)`` for finite a, b, bit for bit."""
    a = abs(a)
    b = abs(b)
    mx = a if a > b else b
    if mx == 0.0:
        return mx
    _, e = math.frexp(mx)
    scale = math.ldexp(1.0, -e)
    csum = 1.0
    frac1 = frac2 = frac3 = 0.0
    for x in (a, b):
        x *= scale
        t = x * T27
        hi = t - (t - x)
        lo = x - hi
        x = hi * hi
        old = csum
        csum += x
        frac1 += (old - csum) + x
        x = 2.0 * hi * lo
        old = csum
        csum += x
        frac2 += (old - csum) + x
        frac3 += lo * lo
    h = math.sqrt(csum - 1.0 + (frac1 + frac2 + frac3))
    t = h * T27
    hi = t - (t - h)
    lo = h - hi
    x = -hi * hi
    old = csum
    csum += x
    frac1 += (old - csum) + x
    x = -2.0 * hi * lo
    old = csum
    csum += x
    frac2 += (old - csum) + x
    x = -lo * lo
    old = csum
    csum += x
    frac3 += (old - csum) + x
    x = csum - 1.0 + (frac1 + frac2 + frac3)
    return (h + x / (2.0 * h)) / scale


@njit(cache=True, inline="always")
def remainder(x, y):
    """IEEE remainder of x by y > 0 (``math.remainder``; exact: fmod is exact and the one
    correction is exact by Sterbenz's lemma; a tie |r| = y/2 keeps r, as an even quotient)."""
    r = np.fmod(x, y)
    if abs(r) > 0.5 * y:
        r = r - y if r > 0.0 else r + y
    return r


@njit(cache=True, inline="always")
def _phase_deg(x, y):
    return math.degrees(math.atan2(-y, x))


@njit(cache=True)
def _lockin_chunk(lf, li, state, samples, first, t_start, drive_phase, drive_freq, tol, out):
    """``LockIn.process`` of one chunk of a continuous stream, reference from the drive:
    outputs into ``out`` rows (t, x, y); returns their count."""
    anchor_span, phase_jump, time_fraction, grid_eps = tol[0], tol[1], tol[2], tol[3]
    interval = lf[LI_INTERVAL]
    if li[LI_HAS_ANCHOR] == 0:
        set_anchor = True
    else:
        a_index = li[LI_A_INDEX]
        n = first - a_index
        c = n * lf[LI_CPS]
        t_pred = lf[LI_A_TIME] + n * interval
        phase_pred = (lf[LI_A_PHASE] + TWO_PI * (c - math.floor(c))) % TWO_PI
        time_jump = abs(t_start - t_pred) > time_fraction * interval
        jump = time_jump
        d = (drive_phase - phase_pred + math.pi) % TWO_PI - math.pi
        if abs(d) > phase_jump or drive_freq != lf[LI_A_FREQ]:
            jump = True
        set_anchor = False
        if jump:
            li[LI_JUMPS] += 1
            if time_jump:
                lf[LI_NEXT_K] = -math.inf
            set_anchor = True
        elif first - a_index > anchor_span:
            set_anchor = True
    if set_anchor:
        li[LI_HAS_ANCHOR] = 1
        li[LI_A_INDEX] = first
        lf[LI_A_TIME] = t_start
        lf[LI_A_PHASE] = drive_phase % TWO_PI
        lf[LI_CPS] = drive_freq * interval
        lf[LI_A_FREQ] = drive_freq
    a_index = li[LI_A_INDEX]
    rate = lf[LI_RATE]
    if lf[LI_NEXT_K] == -math.inf:
        t0 = lf[LI_A_TIME] + (first - a_index) * interval
        lf[LI_NEXT_K] = float(math.ceil(t0 * rate - grid_eps))
    n = samples.shape[0]
    cap = min(n, int(n * interval * rate) + 2)
    out_j = np.empty(cap, dtype=np.int64)
    out_x, out_y, out_t = np.empty(cap), np.empty(cap), np.empty(cap)
    count, lf[LI_NEXT_K] = demodulate(
        samples, first - a_index, lf[LI_A_PHASE], lf[LI_CPS], lf[LI_HARMONIC], lf[LI_A_TIME],
        interval, lf[LI_ALPHA], li[LI_ORDER], state, rate, lf[LI_NEXT_K], out_j, out_x, out_y,
        out_t,
    )  # fmt: skip
    li[LI_NEXT_INDEX] = first + n
    li[LI_CHUNKS] += 1
    li[LI_SAMPLES] += n
    for r in range(count):
        out[r, 0], out[r, 1], out[r, 2] = out_t[r], out_x[r], out_y[r]
    return count


@njit(cache=True)
def _z_update(zf, zi, amplitude, t):
    """``ZController.update`` (enabled, no slew limit); returns the new z [m]."""
    e = zf[Z_SETPOINT] - amplitude
    zf[Z_ERROR] = e
    if zi[Z_HAS_T] == 0:
        dt = 0.0
    elif t > zf[Z_T_LAST]:
        dt = t - zf[Z_T_LAST]
    else:
        dt = 0.0
        zi[Z_NON_MONOTONIC] += 1
    zf[Z_T_LAST] = t
    zi[Z_HAS_T] = 1
    kp, ki, z_lo, z_hi = zf[Z_KP], zf[Z_KI], zf[Z_LO], zf[Z_HI]
    if zi[Z_NEEDS_INIT] != 0:
        zf[Z_INTEGRATOR] = zf[Z_Z] - kp * e
        zi[Z_NEEDS_INIT] = 0
        return zf[Z_Z]
    integrator = zf[Z_INTEGRATOR]
    pe = kp * e
    candidate = integrator + ki * e * dt
    if e > 0.0 and candidate + pe > z_hi:
        candidate = _min(candidate, _max(integrator, z_hi - pe))
    elif e < 0.0 and candidate + pe < z_lo:
        candidate = _max(candidate, _min(integrator, z_lo - pe))
    raw = candidate + pe
    zf[Z_INTEGRATOR] = _min(_max(candidate, z_lo), z_hi)
    z = _min(_max(raw, z_lo), z_hi)
    zf[Z_Z] = z
    return z


@njit(cache=True)
def _pll_update(pf, pi, t, x, y):
    """``OscillationController.update`` of one lock-in output (finite)."""
    if pi[P_HAS_T] == 0 or t <= pf[P_T_LAST]:
        dt = 0.0
    else:
        dt = t - pf[P_T_LAST]
    pf[P_T_LAST] = t
    pi[P_HAS_T] = 1
    amplitude = py_hypot(x, y)
    e = ((_phase_deg(x, y) - pf[P_PHASE_SETPOINT]) + 180.0) % 360.0 - 180.0
    pf[P_PHASE_ERROR], pf[P_AMPLITUDE] = e, amplitude
    if pi[P_PLL_ON] != 0:
        lim = pf[P_RANGE]
        integral = pf[P_INTEGRAL]
        pe = pf[P_PLL_P] * e
        candidate = integral - pf[P_PLL_I] * e * dt
        if candidate - pe > lim:
            candidate = _min(candidate, _max(integral, lim + pe))
        elif candidate - pe < -lim:
            candidate = _max(candidate, _min(integral, -lim + pe))
        pf[P_INTEGRAL] = _min(_max(candidate, -lim), lim)
        pf[P_DF] = _min(_max(candidate - pe, -lim), lim)
    if pi[P_AMP_ON] != 0:
        ea = pf[P_AMP_SETPOINT] - amplitude
        hi = pf[P_DRIVE_MAX]
        integral = pf[P_AMP_INTEGRAL]
        pa = pf[P_AMP_P] * ea
        candidate = integral + pf[P_AMP_I] * ea * dt
        if ea > 0.0 and candidate + pa > hi:
            candidate = _min(candidate, _max(integral, hi - pa))
        elif ea < 0.0 and candidate + pa < 0.0:
            candidate = _max(candidate, _min(integral, -pa))
        pf[P_AMP_INTEGRAL] = _min(_max(candidate, 0.0), hi)
        pf[P_DRIVE] = _min(_max(candidate + pa, 0.0), hi)


@njit(cache=True, nogil=True)
def run_chunks(
    kind, line, c0, c1, count, n_pix, origin_x, origin_y, size, height, material_index,
    size_x, size_y, force_table, model, z, v, k, c, inv_m, dmode, dw, dforce, dphase, dt,
    chunk_steps, every, sigma, seed, scan, zf, zi, pf, pi, lf, li, state1, state2, tol, sums,
    counts, event_beta, event_energy, event_stats,
):  # fmt: skip
    """Chunks ``c0`` to ``c1`` - 1 of ``count`` of a run ``kind`` (ENGAGE at the first pixel,
    TRACE or RETRACE of ``line``) of :class:`BimodalScan`; every state array updated in place.
    Returns (error code, the chunk it happened in)."""
    nsamp = chunk_steps // every
    samples = np.empty((nsamp, 2))
    defl = np.empty(nsamp)
    out1 = np.empty((nsamp + 2, 3))
    out2 = np.empty((nsamp + 2, 3))
    nxt = min(line + 1, n_pix - 1)
    for ch in range(c0, c1):
        row_i = -1
        col_j = -1
        if kind == ENGAGE:
            x, y = origin_x + 0.0 * size, origin_y + (0 + 0.5) / n_pix * size
        elif kind == TRACE:
            frac = (ch + 0.5) / count
            x, y = origin_x + frac * size, origin_y + (line + 0.5) / n_pix * size
            row_i, col_j = line, min(n_pix - 1, int(frac * n_pix))
        else:
            frac = 1.0 - (ch + 0.5) / count
            x, y0 = origin_x + frac * size, origin_y + (line + 0.5) / n_pix * size
            y_next = origin_y + (nxt + 0.5) / n_pix * size
            y = y0 + (ch + 0.5) / count * (y_next - y0)
        h, mat = surface_at(height, material_index, size_x, size_y, x, y)
        z_base = scan[2] - h
        if not math.isfinite(z_base):
            return BAD_Z_BASE, ch
        steps = int(scan[S_STEPS])
        t1 = (steps + every) * dt
        if event_beta > 0.0:  # rk4_event
            advance_two_event(
                z, v, event_energy, k, c, inv_m, dmode, dw, dforce, dphase, model,
                force_table[mat], z_base, dt, chunk_steps, every, samples, sigma, seed, steps,
                event_beta, event_stats,
            )  # fmt: skip
        else:
            advance_two(
                z, v, k, c, inv_m, dmode, dw, dforce, dphase, model, force_table[mat], z_base,
                dt, chunk_steps, every, samples, sigma, seed, steps,
            )  # fmt: skip
        scan[S_STEPS] = steps + chunk_steps
        for s in range(nsamp):
            defl[s] = samples[s, 0] + samples[s, 1]
            if not math.isfinite(defl[s]):
                return BAD_SAMPLES, ch
        index = int(scan[S_INDEX])
        n1 = _lockin_chunk(
            lf[0], li[0], state1, defl, index, t1, dw[0] * t1 + dphase[0], dw[0] / TWO_PI, tol,
            out1,
        )  # fmt: skip
        n2 = _lockin_chunk(
            lf[1], li[1], state2, defl, index, t1, dw[1] * t1 + dphase[1], dw[1] / TWO_PI, tol,
            out2,
        )  # fmt: skip
        scan[S_INDEX] = index + nsamp
        a1_sum = 0.0
        p1_sum = 0.0
        for r in range(n1):
            a = py_hypot(out1[r, 1], out1[r, 2])
            a1_sum += a
            p1_sum += _phase_deg(out1[r, 1], out1[r, 2])
            scan[2] = _z_update(zf, zi, a, out1[r, 0])
        for r in range(n2):
            _pll_update(pf, pi, out2[r, 0], out2[r, 1], out2[r, 2])
        # set_drive(1, frequency, drive): phase continuous at the chunk's end
        w = 2.0 * math.pi * (pf[P_CENTER] + pf[P_DF])
        if w != dw[1]:
            t = (steps + chunk_steps) * dt
            dphase[1] = remainder(dw[1] * t + dphase[1] - w * t, 2.0 * math.pi)
            dw[1] = w
        dforce[1] = pf[P_DRIVE]
        if row_i < 0 or n1 == 0 or n2 == 0:
            continue
        a2_sum = 0.0
        p2_sum = 0.0
        for r in range(n2):
            a2_sum += py_hypot(out2[r, 1], out2[r, 2])
            p2_sum += _phase_deg(out2[r, 1], out2[r, 2])
        sums[0, row_i, col_j] += scan[2]
        sums[1, row_i, col_j] += a1_sum / n1
        sums[2, row_i, col_j] += p1_sum / n1
        sums[3, row_i, col_j] += a2_sum / n2
        sums[4, row_i, col_j] += p2_sum / n2
        sums[5, row_i, col_j] += pf[P_DF]
        sums[6, row_i, col_j] += pf[P_DRIVE]
        counts[row_i, col_j] += 1.0
    return OK, c1


class CompiledLoop:
    """Runs chunks of a :class:`~afm_ros.core.bimodal_scan.BimodalScan` with :func:`run_chunks`,
    its blocks' state packed into arrays for the run and handed back after it."""

    def __init__(self, scan):
        z, lockins = scan.z, scan.lockins
        if z.params["max_slew_rate"] != 0.0 or not z.params["enabled"] or z.fm:
            raise ValueError("the compiled loop runs an enabled amplitude z loop, no slew limit")
        if any(li.params["phase_offset"] != 0.0 for li in lockins) or any(
            li.params["reference_source"] != "drive" for li in lockins
        ):
            raise ValueError("the compiled loop runs drive-referenced lock-ins, no phase offset")
        self.scan = scan
        forces = [scan.forces[name] for name in scan.map.materials]
        models = {f.model_id for f in forces}
        if len(models) != 1:
            raise ValueError("the compiled loop runs one force model for every material")
        (self.model,) = models
        self.force_table = np.array([f.packed() for f in forces])
        self.tol = np.array(continuity_tolerances(), dtype=np.float64)
        self.event_energy = np.zeros((4, 2))  # rk4_event's energies: the session reads none

    def run(self, kind: int, line: int, c0: int, c1: int, count: int) -> None:
        """Chunks c0 .. c1 - 1 of a run (ENGAGE, TRACE, RETRACE of ``line``, ``count`` chunks)."""
        s = self.scan
        sim, z, pll = s.sim, s.z, s.pll
        zs, vs, k, c, inv_m, dmode, dw, dforce, dphase, sigma = sim.kernel_arrays()
        interval = s.values["sample_every"] * s.dt
        lf = np.zeros((2, LI_FLOATS))
        li = np.zeros((2, LI_INTS), dtype=np.int64)
        for j, lockin in enumerate(s.lockins):
            st = lockin.stream_state()
            if st["interval"] is None:  # what the lock-in's first chunk sets
                st["interval"] = interval
                st["alpha"] = lowpass_alpha(interval, lockin.params["time_constant"])
            anchor = st["anchor"]
            if anchor is not None:
                li[j, LI_HAS_ANCHOR], li[j, LI_A_INDEX] = 1, anchor[0]
                lf[j, LI_A_TIME], lf[j, LI_A_PHASE], lf[j, LI_CPS], lf[j, LI_A_FREQ] = anchor[1:]
            li[j, LI_NEXT_INDEX] = -1 if st["next_index"] is None else st["next_index"]
            li[j, LI_CHUNKS], li[j, LI_SAMPLES] = st["chunks"], st["samples"]
            li[j, LI_JUMPS], li[j, LI_ORDER] = st["reference_jumps"], lockin.params["filter_order"]
            lf[j, LI_NEXT_K], lf[j, LI_ALPHA] = st["next_k"], st["alpha"]
            lf[j, LI_INTERVAL], lf[j, LI_RATE] = st["interval"], lockin.params["output_rate"]
            lf[j, LI_HARMONIC] = float(lockin.params["harmonic"])
        zp = z.params
        zf = np.array([
            z.z, z.integrator, z.error, 0.0 if z.t_last is None else z.t_last, zp["setpoint"],
            zp["p_gain"], zp["i_gain"], zp["z_min"], zp["z_max"],
        ])  # fmt: skip
        zi = np.array(
            [z.t_last is not None, z.needs_init, z.non_monotonic_samples], dtype=np.int64
        )
        pp = pll.params
        pf = np.array([
            pll.integral, pll.df, pll.drive, pll.amp_integral, pll.phase_error, pll.amplitude,
            0.0 if pll.t_last is None else pll.t_last, pp["center_frequency"],
            pp["phase_setpoint"], pp["pll_p_gain"], pp["pll_i_gain"], pp["frequency_range"],
            pp["amplitude_setpoint"], pp["amplitude_p_gain"], pp["amplitude_i_gain"],
            pp["drive_max"],
        ])  # fmt: skip
        pi = np.array(
            [pll.t_last is not None, pp["pll_enabled"], pp["amplitude_enabled"]], dtype=np.int64
        )
        state = np.array([float(sim.steps), float(s.index), s.z_piezo])
        m = s.map
        code, where = run_chunks(
            kind, line, c0, c1, count, s.n, s.origin[0], s.origin[1], s.size, m.height,
            m.material_index, m.size_x, m.size_y, self.force_table, self.model, zs, vs, k, c,
            inv_m, dmode, dw, dforce, dphase, s.dt, s.chunk_steps, s.values["sample_every"],
            sigma, sim.seed, state, zf, zi, pf, pi, lf, li, s.lockins[0].state,
            s.lockins[1].state, self.tol, s.sums, s.counts,
            modes_events.BETA if sim.integrator == "rk4_event" else 0.0, self.event_energy,
            sim.event_stats,
        )  # fmt: skip
        # hand the state back, also after a refused chunk (the chunks before it count)
        sim.steps, s.index, s.z_piezo = int(state[0]), int(state[1]), float(state[2])
        sim.drives_changed()
        z.z, z.integrator, z.error = float(zf[Z_Z]), float(zf[Z_INTEGRATOR]), float(zf[Z_ERROR])
        z.t_last = float(zf[Z_T_LAST]) if zi[Z_HAS_T] else None
        z.needs_init, z.non_monotonic_samples = bool(zi[Z_NEEDS_INIT]), int(zi[Z_NON_MONOTONIC])
        pll.integral, pll.df, pll.drive = (
            float(pf[P_INTEGRAL]),
            float(pf[P_DF]),
            float(pf[P_DRIVE]),
        )
        pll.amp_integral = float(pf[P_AMP_INTEGRAL])
        pll.phase_error, pll.amplitude = float(pf[P_PHASE_ERROR]), float(pf[P_AMPLITUDE])
        pll.t_last = float(pf[P_T_LAST]) if pi[P_HAS_T] else None
        for j, lockin in enumerate(s.lockins):
            anchor = None
            if li[j, LI_HAS_ANCHOR]:
                anchor = (int(li[j, LI_A_INDEX]), *(float(lf[j, i]) for i in range(4)))
            lockin.restore_stream_state({
                "anchor": anchor,
                "next_index": None if li[j, LI_NEXT_INDEX] < 0 else int(li[j, LI_NEXT_INDEX]),
                "next_k": float(lf[j, LI_NEXT_K]), "alpha": float(lf[j, LI_ALPHA]),
                "interval": float(lf[j, LI_INTERVAL]), "chunks": int(li[j, LI_CHUNKS]),
                "samples": int(li[j, LI_SAMPLES]), "reference_jumps": int(li[j, LI_JUMPS]),
            })  # fmt: skip
        if code == BAD_Z_BASE:
            raise ValueError(f"z_base is not finite at chunk {where} (z piezo {s.z_piezo!r} m)")
        if code == BAD_SAMPLES:
            raise ValueError(f"the deflection is not finite in chunk {where}: a runaway")
