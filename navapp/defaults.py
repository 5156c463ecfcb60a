"""Named defaults shared by the library, the CLI, the app and the studies.

``EDGE_MM`` and ``K`` are the registration model the paper-scale results use: a tet mesh of
the preoperative liver with 4 mm target edges and k = 45 control points (the paper's
value, §II-B; the cost study, ``results/cost.md``, measures other k and edges).
"""

EDGE_MM = 4.0
"""Target tet edge length of the registration mesh, mm."""
K = 45
"""Number of control points k (the basis has 3k modes; β has 3k + 6 entries)."""
