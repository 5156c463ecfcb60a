"""Probe: where local modes are kept and the answer comes from ICP's pose (which the
cross-validation alone judges), how large is the correction against its own σ
(``support.weigh_correction``), beside the TRE of the answer, of the rigid answer and of no
correction? JSON lines appended to OUT, one per registration whose modes were kept.

    python notes/scripts/local_modes_z.py OUT.jsonl CASE [CASE ...]
"""

import json
import sys
import warnings
from dataclasses import replace
from pathlib import Path

from navapp.geometry.tre import mean_tre
from navapp.registration.local_modes import LocalModeOptions
from navapp.registration.pipeline import RobustOptions, _settings, register
from navapp.registration.support import SupportOptions, weigh_correction

sys.path.insert(0, str(Path(__file__).parent))
from local_modes_probe import each_case, each_level  # noqa: E402


def main(out_path, cases):
    with open(out_path, "a") as out:
        for c, case, model in each_case(cases):
            x0, x1 = case.need_truth().tre_points(model.basis.nodes)
            for level, data in each_level(c, case):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    reg = register(model, data, init=RobustOptions(local_modes=LocalModeOptions()))
                    rigid = register(model, data, deform=False)
                if reg.local_modes is None or not reg.local_modes.adopted or reg.support is None:
                    continue
                options = replace(_settings(None, None)[0], pose=not reg.rigid.kept)
                s = weigh_correction(reg.model, reg.data_model_frame, reg.libr.beta, reg.support, options,
                                     SupportOptions())
                row = {"case": c.name, "level": level, "kept": reg.rigid.kept, "deformed": reg.deformed,
                       "warned": bool(reg.warnings), "z": round(s.correction_mm / s.sigma_mm, 2),
                       "correction_mm": round(s.correction_mm, 2), "sigma_mm": round(s.sigma_mm, 2),
                       "tre": round(mean_tre(reg.transform(x0), x1), 3),
                       "tre_rigid": round(mean_tre(rigid.transform(x0), x1), 3),
                       "tre_identity": round(mean_tre(x0, x1), 3)}
                print(json.dumps(row), file=out, flush=True)
                print(row, flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
