"""Where LM finds the closest points on a deforming model surface.

A model surface at β is x = R(θ)·local + τ + x̄0 with local = x0 − x̄0 + J_u α (eq. 8). The
closest point is unchanged by a rigid motion applied to both the surface and the point, so
the data are carried into the surface's local frame, y_local = Rᵀ(y − τ − x̄0), and searched
there: the surface then moves only by its deformation between evaluations, and one
hierarchy per model surface (``geometry.surface_search.SurfaceSearch``), built on the
undeformed surface at first use, is refit rather than rebuilt for the rest of the model's life — every LM
iteration and every live frame. The data, which are fixed, are never the thing indexed:
the query is a data point against the moving surface.
"""

import numpy as np

from ..geometry.surface_search import SurfaceSearch
from .model import ModelFeature, RegistrationModel
from .rotation import rotation


def surface_search(model: RegistrationModel, feat: ModelFeature) -> SurfaceSearch:
    """The model's one search structure for surface feature ``feat`` (made on first use)."""
    searches = model.cache.setdefault("surface_search", {})
    key = id(feat)
    found = searches.get(key)
    if found is None or found[0] is not feat:
        found = searches[key] = (feat, SurfaceSearch(feat.cells, feat.rest - model.centroid))
    return found[1]


class PlacedSurface:
    """A surface feature's deformed, unrotated points ``local`` (V, 3) mm at β: its closest
    points to data in the model frame (``closest``), searched in the local frame."""

    def __init__(self, search: SurfaceSearch, local: np.ndarray, beta: np.ndarray, centroid: np.ndarray):
        n = len(beta) - 6
        self.search, self.local = search, local
        self.R, self.shift = rotation(beta[n + 3:n + 6]), beta[n:n + 3] + centroid
        search.prepare(local)  # refit now: timed with the geometry, shared by the features using it

    def closest(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """face (N,) and barycentric weights (N, 3) of the closest surface points to Y (N, 3) mm."""
        face, bary, _ = self.search.closest((np.asarray(Y, float) - self.shift) @ self.R, self.local)
        return face, bary


def placed_surface(model: RegistrationModel, feat: ModelFeature, local: np.ndarray, beta) -> PlacedSurface:
    """``PlacedSurface`` of surface feature ``feat`` at β (``local`` from ``model.positions``)."""
    return PlacedSurface(surface_search(model, feat), local, np.asarray(beta, float), model.centroid)
