"""Where a registration's time goes: wall and CPU seconds per stage (``Registration.stages``).

``register`` marks the end of each stage (the multi-start ICP, the basin screening, the pose
choice, the deformable fits, the cross-validation, the error estimate, …); a stage's time is
what passed since the previous mark, so the stages add up to the whole call. CPU is the
process's (every thread), so on a machine other work shares, CPU says what the stage costs and
wall what it took (``navapp bench register`` prints both). Work run on the second thread among a
stage's own (the error estimate beside the cross-validation's folds) counts in that stage. Where
two stages run side by side on two cores they are one lap: ``rigid_search`` (the multi-start ICP
and the screening beside the pose choice's trimmed fit; ``pose_choice`` then holds the rest of
the choice) and ``deformable+support`` (the deformable fit beside the cross-validation's folds
and the error estimate; ``deformable`` and ``support`` then hold what follows each).
"""

import time
from dataclasses import dataclass


@dataclass(frozen=True)
class StageTime:
    """One stage's seconds: ``wall`` elapsed, ``cpu`` this process's CPU time over it."""

    wall: float
    cpu: float

    def __add__(self, other: "StageTime") -> "StageTime":
        return StageTime(self.wall + other.wall, self.cpu + other.cpu)


class StageClock:
    """Laps of one call: ``mark(name)`` adds the time since the last mark to ``name``."""

    def __init__(self) -> None:
        self.times: dict[str, StageTime] = {}
        self._wall, self._cpu = time.perf_counter(), time.process_time()

    def mark(self, name: str) -> None:
        wall, cpu = time.perf_counter(), time.process_time()
        lap = StageTime(wall - self._wall, cpu - self._cpu)
        self.times[name] = self.times[name] + lap if name in self.times else lap
        self._wall, self._cpu = wall, cpu
