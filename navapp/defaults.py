"""Named defaults shared by the library, the CLI, the app and the studies.

``EDGE_MM`` and ``K`` are the registration model the paper-scale results use: a tet mesh of
the preoperative liver with 4 mm target edges and k = 45 control points (the paper's
value, §II-B; the cost study, ``results/cost.md``, measures other k and edges).
"""

EDGE_MM = 4.0
"""Target tet edge length of the registration mesh, mm."""
K = 45
"""Number of control points k (the basis has 3k modes; β has 3k + 6 entries)."""

LM_MAX_ITERATIONS = 100
"""Levenberg–Marquardt iteration cap of a registration (``LMOptions.max_iterations``)."""

PROBE_WIDTH_PX, PROBE_HEIGHT_PX, PROBE_SPACING_MM = 256, 320, 0.25
"""The simulated linear probe's image: 256 × 320 pixels of 0.25 mm (64 mm wide, 80 mm deep)."""
FAR_WALL_COS, FAR_WALL_MIN_DEPTH_MM = 0.2, 15.0
"""The posterior (far) liver wall an iUS image shows: liver faces turned away from the probe
(normal · depth axis > 0.2), more than 15 mm deep. The simulator segments it so, and the
next-plane planner expects it so."""
N_PLANES = 16
"""iUS planes a simulated scene records: 8 vertical + 8 lateral (``ius.planes``' default and
maximum); a study's "S+all" registers all of them."""

DISPLAY_FACES = 4_000
"""Triangles the viewer draws at most for a preoperative or true liver: quadric decimation,
``app.display``. Every tab redraws its whole scene in software on a machine without a GPU
(viser's once-a-second heartbeat and every change), and an idle frame's cost follows the
triangles drawn, whatever their size on screen; what the registration fits is not touched. On
the phantoms the drawn liver lies within 0.25 mm of the surface both ways (docs/decisions/viewer.md,
"What a tab draws" and "issue 50 item 7, session 35")."""
DISPLAY_VESSEL_FACES = 2_000
"""Triangles the viewer draws at most for a preoperative vessel tree (``DISPLAY_FACES``' reason):
within 0.25 mm of the vessel's surface both ways on the phantoms."""
