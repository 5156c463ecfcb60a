"""The viewer shows the lines ``Registration.warnings`` decides stand for an answer, and no
check's own line beside them (issue 51, item 2: one ``Warning`` type carried from where it is
found to every place that shows it). Before, the reason beside each target of a pose-alone
answer was ``reg.support.warning`` read directly, and a warm start's row carried
``checked.organ.warning`` read directly: each said a line the run's own row, result.json and
Slicer's status line did not."""

import json
import types
from dataclasses import replace

import numpy as np
from test_local_loads import _dented_scan

from navapp.app.runs import fit_notice
from navapp.app.shown import Shown
from navapp.app.state import CARRIED, RunEntry, RunKind
from navapp.fitwarning import FitWarning, WarningKind
from navapp.registration.uncertainty import OrganError, PoseEvidence
from navapp.tracking.results import status_line


def _bands(reg, centres):
    """What the viewer writes beside each target for ``reg`` (``Shown.predict``)."""
    core = types.SimpleNamespace(preop=types.SimpleNamespace(
        targets=[types.SimpleNamespace(name=f"tumour{i + 1}", centre=c) for i, c in enumerate(centres)]))
    _, bands = Shown.predict(types.SimpleNamespace(core=core), reg)
    return bands


def test_beside_the_targets_of_a_pose_alone_only_a_line_the_registration_says(small_model, phantoms):
    data, _ = _dented_scan(phantoms[0].liver.vertices, small_model, 30.0, 15.0, far_mm=50.0)
    from navapp.registration.pipeline import register

    reg = register(small_model, data)
    centres = [data["anterior"].mean(0), small_model.basis.nodes.mean(0)]
    assert not reg.deformed and reg.support is not None and reg.support.warning  # the pose alone (test_local_loads)
    why = reg.why_pose_alone
    assert why is not None and why in reg.warnings and why.kind is WarningKind.UNSUPPORTED
    bands = _bands(reg, centres)
    assert [b.warning for b in bands] == [FitWarning(why.kind, why.head)] * 2
    assert all(not np.isfinite(b.predicted_mm) for b in bands)
    assert all(b.text() == f"⚠ {why.head}" for b in bands)

    # a declared pose the data confirm: the pose alone is shown without a line (PoseEvidence), so
    # ``warnings`` is empty though the cross-validation's own line is not; nothing beside the targets
    # (and no coverage note: ``register`` makes none where a declared pose's evidence says how far off it may be)
    quiet = replace(reg, notes=[], pose_evidence=PoseEvidence(moved_mm=0.2, sigma_mm=1.0, prior_sigma_mm=1.5,
                                                              misfit_sigma_mm=1.2))
    assert quiet.pose_evidence.warning is None and quiet.support.warning and not quiet.deformed
    assert quiet.warnings == [] and quiet.why_pose_alone is None
    assert [b.warning for b in _bands(quiet, centres)] == [None, None]
    assert all(b.text() == "" for b in _bands(quiet, centres))
    assert "fit ok" in status_line(quiet)  # Slicer is told the same

    # a declared pose the data leave open: its own line's head, not the cross-validation's
    loud = replace(reg, notes=[], pose_evidence=PoseEvidence(moved_mm=0.2, sigma_mm=1.0, prior_sigma_mm=9.0))
    line = loud.pose_evidence.warning
    assert loud.warnings == [FitWarning(WarningKind.POSE_EVIDENCE, line)] and loud.why_pose_alone == loud.warnings[0]
    assert [b.warning for b in _bands(loud, centres)] == [FitWarning(WarningKind.POSE_EVIDENCE, line.split(":")[0])] * 2


def test_a_warm_start_carries_the_organ_line_its_fresh_fit_said_and_only_that(small_model, phantoms):
    from navapp.registration.pipeline import register

    data, _ = _dented_scan(phantoms[0].liver.vertices, small_model, 30.0, 15.0, far_mm=50.0)
    fitted = register(small_model, data)
    # the fresh fit, made deformed and without a doubt about its pose, its organ error over the margin
    fresh = replace(fitted, support=None, notes=[], determinacy=None, pose_choice=None, quality=None,
                    organ=OrganError(mean_mm=50.0, nodes=1500))
    organ = fresh.organ.warning
    assert fresh.deformed and organ and fresh.warnings == [FitWarning(WarningKind.ORGAN_ERROR, organ)]
    warm = replace(fresh, organ=None)  # a warm start repeats neither check
    assert warm.warnings == []
    warm.carry(fresh, CARRIED)
    said = f"{organ} ({CARRIED})"
    assert warm.warnings == [FitWarning(WarningKind.ORGAN_ERROR, said, carried=True)]
    # one list for every place that shows it: the row, the red box (before, "⚠ ." with the row's
    # line and no head) and Slicer's status line (before, "fit ok")
    assert RunEntry.of(RunKind.WARM, warm, 100, 1.0).warning == said
    assert fit_notice(warm.warnings, False).startswith(f"⚠ {organ.split(':')[0]}.")
    assert "fit ok" not in status_line(warm) and "oncological margin" in status_line(warm)
    fresh.carry(fresh, CARRIED)
    assert fresh.carried == []  # the fit that made the check says it itself

    # the fresh fit's pose in doubt: its own row has no organ line (no figure beside a pose not
    # to be believed), and a warm start from it carries none either
    doubted = replace(fresh, notes=[FitWarning(WarningKind.COVERAGE, "too little of the liver covered: 4 %")])
    assert doubted.organ.warning and all(w.kind is not WarningKind.ORGAN_ERROR for w in doubted.warnings)
    warm.carry(doubted, CARRIED)
    assert warm.warnings == [] and RunEntry.of(RunKind.WARM, warm, 100, 1.0).warning is None
    # and a warm answer whose own pose is in doubt says no carried figure beside it
    warm.carry(fresh, CARRIED)
    assert replace(warm, notes=doubted.notes).warnings == doubted.notes


def test_a_targets_line_is_a_fitwarning_from_where_it_is_found():
    """``support.TargetSupport.warning`` makes the target's line, its kind TARGET, and marks it
    carried where it rests on a block verdict carried from the fresh fit (the distance to the
    data is this answer's own): the texts the viewer and result.json show today."""
    from navapp.registration.support import SupportOptions, TargetSupport

    near = "deformation not determined by the data near tumour1: "
    block = near + "the data around it are not predicted better by the deformation than without it"
    assert TargetSupport("tumour1", 5.0, False).warning == FitWarning(WarningKind.TARGET, block)
    assert TargetSupport("tumour1", 5.0, False, said=CARRIED).warning == \
        FitWarning(WarningKind.TARGET, f"{block} ({CARRIED})", carried=True)
    far = SupportOptions.far_mm + 30.0
    line = near + f"no data within {SupportOptions.far_mm:g} mm (nearest {far:.0f} mm)"
    assert TargetSupport("tumour1", far, None, said=CARRIED).warning == FitWarning(WarningKind.TARGET, line)
    assert TargetSupport("tumour1", 5.0, True, said=CARRIED).warning is None


def test_a_target_line_is_shown_by_its_flag_never_by_its_words():
    """The 2D view's short form says "(last full registration)" for a line marked carried, whatever
    its words; before, ``TargetBand.text`` searched the line for ``CARRIED``'s words. The session
    keeps the kind and the flag; a session of before, the text alone, reads back as a saved line."""
    from navapp.app.state import TargetBand

    marked = TargetBand("tumour1", 4.0, 2.0, 7.0, FitWarning(WarningKind.TARGET, "a line near tumour1: why",
                                                             carried=True))
    assert marked.text(short=True) == "predicted error 4.0 mm (2.0–7.0) ⚠ a line near tumour1 (last full registration)"
    assert marked.text() == "predicted error 4.0 mm (2.0–7.0) ⚠ a line near tumour1: why"
    worded = TargetBand("tumour1", 4.0, 2.0, 7.0,
                        FitWarning(WarningKind.TARGET, f"a line near tumour1: why ({CARRIED})"))
    assert worded.text(short=True) == "predicted error 4.0 mm (2.0–7.0) ⚠ a line near tumour1"
    assert TargetBand.from_json(json.loads(json.dumps(marked.to_json()))) == marked
    assert TargetBand.from_json(json.loads(json.dumps(worded.to_json()))) == worded
    old = TargetBand.from_json(["tumour1", 4.0, 2.0, 7.0, "a line near tumour1: why"])
    assert old.warning == FitWarning(WarningKind.SAVED, "a line near tumour1: why")
    assert TargetBand.from_json(["tumour1", 4.0, 2.0, 7.0]).warning is None
