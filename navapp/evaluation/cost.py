"""What accuracy costs in time: the same data registered at several settings, each row
giving the seconds spent and the TRE reached, and the Pareto front of (time, TRE).

``lm_sweep`` varies only the solve (LM iteration cap and stopping tolerance) on one
registration model, so it runs in seconds and serves the viewer's settings panel; the
study command (``navapp study cost``) adds the settings that need a new basis (k, mesh
edge) and the amount of data (planes).
"""

import time
from dataclasses import dataclass

import numpy as np

from ..registration.libr import LMOptions
from ..registration.pipeline import register, tre_stats

LM_CAPS = (0, 1, 2, 4, 8, 16, 100)  # 0 = rigid only
LM_RTOLS = (1e-1, 1e-2, 1e-3)


@dataclass
class CostRow:
    label: str
    seconds: float  # wall time of the registration (rigid ICP included)
    tre_mean_mm: float
    iterations: int
    settings: dict


def run_setting(model, data, x0, x1, label, options: LMOptions | None = None, deform=True, **settings) -> CostRow:
    """Register ``data`` once; TRE of the registered preoperative points ``x0`` (T, 3)
    against their true positions ``x1`` (T, 3), mm."""
    t = time.perf_counter()
    reg = register(model, data, deform=deform, options=options)
    sec = time.perf_counter() - t
    tre = tre_stats(reg.transform(x0), x1)["mean_mm"]
    return CostRow(label, sec, tre, reg.libr.iterations if reg.libr else 0, settings)


def lm_sweep(model, data, x0, x1, caps=LM_CAPS, rtols=LM_RTOLS, cancel=None, on_row=None) -> list[CostRow]:
    """Rows for each iteration cap (at the default tolerance) and each tolerance (no cap).
    ``cancel`` (threading.Event) stops between settings; ``on_row`` sees each row as it lands."""
    plan = [(f"{c} it" if c else "rigid", LMOptions(max_iterations=max(c, 1)), c > 0, {"max_iterations": c})
            for c in caps]
    plan += [(f"rtol {r:g}", LMOptions(rtol=r), True, {"rtol": r}) for r in rtols]
    rows = []
    for label, opt, deform, settings in plan:
        if cancel is not None and cancel.is_set():
            break
        row = run_setting(model, data, x0, x1, label, opt, deform, **settings)
        rows.append(row)
        if on_row is not None:
            on_row(row)
    return rows


def pareto_front(seconds, errors) -> np.ndarray:
    """Boolean mask (N,) of the points no other point beats in both time and error
    (ties kept); the front a user picks a setting from."""
    t, e = np.asarray(seconds, float), np.asarray(errors, float)
    keep = np.ones(len(t), bool)
    for i in range(len(t)):
        dominated = (t <= t[i]) & (e <= e[i]) & ((t < t[i]) | (e < e[i]))
        keep[i] = not dominated.any()
    return keep
