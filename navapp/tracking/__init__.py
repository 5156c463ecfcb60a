"""Live tracking over OpenIGTLink: headless, no viser; I/O only (the re-registration of live
data is ``registration.live``, its benchmark ``evaluation.live_bench``).

- ``config``: the TOML config: the connection, watchdog timeouts and digitising rate, and each
  tool's own settings read by its receiver (PLUS device names, ImageToProbe, a tool's pose);
- ``events``: the typed events the app receives (StylusSample, ProbePose, ProbeSample, ToolStatus,
  ConnectionStatus, Skipped, TransformSample);
- ``client``: ``TrackingClient``, an OpenIGTLink client thread (pyigtl) checking every message
  and handing it to its source's receiver;
- ``receivers``: the receiving side of each tracked data source, found from ``features.TABLE``
  (the stylus's tip stream, the probe's pose and frames, a source's POINT messages, in
  Reference or placed by the tool's own pose);
- ``watchdog``: per-device seen / stale / missing;
- ``digitiser``: ``Digitiser``, stylus points at a set rate while recording;
- ``replay``: ``ReplayServer``, a PLUS-like server playing a simulated scene (``navapp replay``);
- ``results``: ``ResultsSender``, registrations back to 3D Slicer (TRANSFORM, POINT, STRING);

Frames: tracker coordinates (PLUS's Reference frame, mm) are passed through unchanged. The
preoperative model is in navapp's LAS frame; registration's rigid part maps model → tracker
space and so absorbs the tracker-to-patient transform, whatever the tracker's axes are.
"""

from .config import TrackingConfig, load_config
from .digitiser import Digitiser
from .events import ConnectionStatus, ProbePose, ProbeSample, Skipped, StylusSample, ToolStatus, TransformSample

__all__ = ["TrackingConfig", "load_config", "Digitiser", "ConnectionStatus", "ProbePose",
           "ProbeSample", "Skipped", "StylusSample", "ToolStatus", "TransformSample", "TrackingClient", "ReplayServer",
           "ResultsSender"]


def __getattr__(name):  # the networking modules load on first use
    if name == "TrackingClient":
        from .client import TrackingClient
        return TrackingClient
    if name == "ReplayServer":
        from .replay import ReplayServer
        return ReplayServer
    if name == "ResultsSender":
        from .results import ResultsSender
        return ResultsSender
    raise AttributeError(name)
