"""``afm_ctl bimodal frame|stop [--wait]``: the bimodal node from the command line (its frame's
progress, then E* per material against the truth); the command is afm_ctl's
(:mod:`afm_ros.tools.afm_ctl`)."""

from __future__ import annotations

import time

from afm_ros.client import NoAnswer


def _number(value, scale: float, digits: int) -> str:
    return "n/a" if value is None else f"{value * scale:.{digits}f}"


def cmd_bimodal(link, args, out) -> int:
    """The bimodal node: frame (a frame with its parameters), stop (after the line under way);
    frame --wait: a line per scanned line, then the per-material table (exit 1 unless done)."""
    service = {"frame": "bimodal/scan_frame", "stop": "bimodal/stop"}[args.action]
    if not args.wait:
        print(link.trigger(service, node="bimodal"), file=out, flush=True)
        return 0
    progress: list = []
    tables: list = []
    subs = [
        link.on_progress(progress.append, "bimodal/progress"),
        link.on_progress(tables.append, "bimodal/materials"),
    ]
    try:
        answer = link.trigger(service, node="bimodal")
        print(answer, file=out, flush=True)
        frame = int(answer.split()[1].rstrip(":"))  # "frame N: ..."
        shown, last = 0, time.monotonic()
        while True:
            mine = [p for p in progress if p.get("frame") == frame]
            if mine and mine[-1]["lines_done"] > shown:
                p = mine[-1]
                shown, last = p["lines_done"], time.monotonic()
                print(
                    f"  line {shown}/{p['lines']}, {p['simulated_s']:.3f} s simulated, "
                    f"{p['real_time_factor']:.2f} x real time",
                    file=out,
                    flush=True,
                )
            if mine and mine[-1]["state"] != "scanning":
                break
            if time.monotonic() - last > args.timeout:
                raise NoAnswer(f"{link.resolve('bimodal/progress')} (a line)", args.timeout)
            link.spin_for(0.1)
        end = mine[-1]
        rows = next((t["materials"] for t in reversed(tables) if t.get("frame") == frame), [])
        print(f"frame {frame} {end['state']}: {end['lines_done']} of {end['lines']} lines"
              + (f", {end['file']}" if end["file"] else "")
              + (f" ({end['reason']})" if end["reason"] else ""), file=out)  # fmt: skip
        for r in rows:
            e, true = r["modulus"], r["true_modulus"]
            bias = "" if e is None else f" ({r['bias'] * 100:+.1f} %)"
            shown_e = "no estimate" if e is None else f"{e / 1e9:.3f} GPa"
            print(
                f"  {r['material']:<12} E* {shown_e} against {true / 1e9:.3f} GPa true{bias}, "
                f"df2 {_number(r['frequency_shift_2'], 1.0, 1)} Hz, "
                f"height {_number(r['height'], 1e9, 2)} nm",
                file=out,
            )
        return 0 if end["state"] == "done" else 1
    finally:
        for sub in subs:
            link.node.destroy_subscription(sub)
