"""The local modes as ``register`` now runs them (``RobustOptions.local_modes``), beside the
default, per case and level (S, S + all): mean TRE of both answers and of both deformable
fits (shown or not), whether the modes were kept, the held-out RMS either way, the
warnings, and the seconds. JSON lines appended to OUT.

    python notes/scripts/local_modes_pipeline.py OUT.jsonl CASE [CASE ...]
"""

import json
import sys
import time
import warnings
from pathlib import Path

from navapp.geometry.tre import mean_tre
from navapp.registration.local_modes import LocalModeOptions
from navapp.registration.pipeline import RobustOptions, register

sys.path.insert(0, str(Path(__file__).parent))
from local_modes_probe import each_case, each_level  # noqa: E402


def main(out_path, cases):
    with open(out_path, "a") as out:
        for c, case, model in each_case(cases):
            x0, x1 = case.need_truth().tre_points(model.basis.nodes)
            for level, data in each_level(c, case):
                row = {"case": c.name, "level": level}
                local = RobustOptions(local_modes=LocalModeOptions())
                for name, init in (("default", RobustOptions()), ("local", local)):
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")  # collected from the Registration instead
                        t = time.perf_counter()
                        reg = register(model, data, init=init)
                        sec = time.perf_counter() - t
                    fit = reg.transform(x0, beta=reg.libr.beta)  # the deformable fit, shown or not
                    row[name] = {"tre": round(mean_tre(reg.transform(x0), x1), 3),
                                 "tre_fit": round(mean_tre(fit, x1), 3),
                                 "answer": "deformable" if reg.deformed else "rigid", "warned": bool(reg.warnings),
                                 "first": reg.warnings[0][:60] if reg.warnings else "", "s": round(sec, 2)}
                    if reg.local_modes is not None:
                        row[name]["modes"] = reg.local_modes.as_dict()
                print(json.dumps(row), file=out, flush=True)
                print(row, flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
