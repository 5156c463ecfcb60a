"""The 2D ultrasound view, where contours are drawn: ``http`` (the server, in a thread),
``page.html`` / ``page.js`` (the page, a canvas), ``provider`` (what a tab's page shows and
what its clicks do) and ``overlays`` (the model cut by the image plane). No viser here."""

from .http import POLL_MS, Provider, View2DServer

__all__ = ["POLL_MS", "Provider", "View2DServer"]
