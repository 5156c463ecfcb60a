"""The guided demo: the steps a newcomer is walked through, each a short explanation and
the one action its button performs (an ``App`` method name). No viser here."""

from dataclasses import dataclass


@dataclass(frozen=True)
class Step:
    title: str
    text: str
    button: str
    action: str  # name of the App method the button calls


STEPS = (
    Step("Preoperative model",
         "The liver segmented from the preoperative CT (semi-transparent), its portal vein (red) and "
         "hepatic veins (blue) with their centerlines. Everything the surgeon navigates by lives here.",
         "Show the preoperative model", "guide_preop"),
    Step("Intraoperative deformation",
         "In theatre the liver is mobilised and packed: it sags and twists away from its CT shape. "
         "The green ghost is the true deformed liver of this simulated case; the system never sees it.",
         "Show the true deformed liver", "guide_truth"),
    Step("Stylus digitisation",
         "A tracked stylus is swept over the exposed anterior surface; every few millimetres its tip "
         "position is recorded. Only about a fifth of the anterior surface is reachable.",
         "Digitise the anterior surface", "guide_stylus"),
    Step("Rigid registration",
         "First a rigid fit (weighted ICP on the salient features: falciform ligament and inferior "
         "ridges). The error colours show what a rigid fit cannot fix.",
         "Register rigidly", "guide_rigid"),
    Step("Deformable registration, surface only",
         "LIBR deforms the model with a linear-elastic basis of boundary modes until it matches the "
         "stylus data, keeping strain energy low. Watch it converge live.",
         "Register deformably (surface data)", "guide_surface"),
    Step("Add an ultrasound plane",
         "A tracked ultrasound probe images the liver's interior; the B-mode image is shown at its "
         "true pose in 3D.",
         "Acquire plane 1", "guide_plane"),
    Step("Draw contours",
         "Designate features on the image: pick a type, click on the image to place vertices, close "
         "the contour. Clicks become image pixels (Bresenham between vertices) and then 3D points "
         "through the probe's calibration and tracking. Or let the simulation segment it.",
         "Open the drawing view", "guide_draw"),
    Step("Register with ultrasound",
         "Deformable registration with everything: stylus surface, the drawn vessel contours, their "
         "centerline points and the posterior wall. It warm-starts from the last result.",
         "Register deformably (all data)", "guide_all"),
    Step("Compare errors",
         "Each registration's mean and maximum error against the true deformation, and its time.",
         "Show the comparison", "guide_compare"),
)
