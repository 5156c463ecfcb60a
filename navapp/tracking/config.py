"""Live-tracking configuration: which OpenIGTLink devices to listen to, the probe
calibration, the watchdog timeouts and the digitising rate, from a small TOML file.

Defaults are PLUS's usual names: a PlusServer with a pivot-calibrated stylus sends
``StylusTipToReference``, a tracked probe ``ProbeToReference``, and an image stream declared
as ``<Image Name="Image" EmbeddedTransformToFrame="Reference"/>`` arrives as the IMAGE device
``Image_Reference`` whose matrix already is ImageToReference (pixels → mm). Example::

    [server]
    host = "127.0.0.1"
    port = 18944
    [devices]
    stylus = "StylusTipToReference"
    probe = "ProbeToReference"
    image = "Image_Reference"
    image_pose = "embedded"      # or "calibration": ProbeToReference · ImageToProbe below
    [calibration]
    image_to_probe = [[0.25, 0, 0, -31.875], [0, 0, -0.25, 0], [0, 0.25, 0, 0], [0, 0, 0, 1]]
    [watchdog]
    stale_s = 0.2                # older than this: "stale"
    missing_s = 1.0              # older than this, or never seen: "missing"
    [digitiser]
    rate_hz = 10.0               # stylus points recorded per second while recording
    [tools.laparoscope]          # a tracked data source (``features.SOURCED``), optional
    pose = "CameraToReference"     # its points arrive in its own frame, placed by this TRANSFORM

Without a ``[tools.<source>]`` table a source's POINT messages are in Reference already.

A bad file ends in one line naming the file and the key (``InputError``).
"""

import tomllib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..features import SOURCED, TABLE
from ..simulation.probe import Probe

DEFAULT_PORT = 18944  # OpenIGTLink's registered port, PLUS's and Slicer's default


def full_image_matrix(m) -> np.ndarray:
    """An image-to-frame 4×4 whose third (slice) column is the image plane's normal at the
    column spacing. navapp's ``Probe.image_to_probe`` leaves that column degenerate (pixels
    have k = 0, so it never mattered); OpenIGTLink, PLUS and Slicer need it invertible."""
    m = np.array(m, float)
    n = np.cross(m[:3, 0], m[:3, 1])
    if np.linalg.norm(n) > 0:
        m[:3, 2] = n / np.linalg.norm(n) * np.linalg.norm(m[:3, 0])
    return m


def _default_image_to_probe():
    return full_image_matrix(Probe().image_to_probe())


@dataclass(frozen=True)
class ToolDevices:
    """A tracked data source's own devices (``[tools.<source>]``): ``pose`` is the TRANSFORM
    (ToolToReference, mm) that places its POINT messages, which then arrive in the tool's
    own frame (a tracked laparoscope's camera frame); a source without one sends them in
    Reference."""

    source: str  # a ``features.TABLE`` source with features in ``features.SOURCED``
    pose: str  # its TRANSFORM's device name


@dataclass(frozen=True)
class TrackingConfig:
    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    stylus: str = "StylusTipToReference"
    probe: str = "ProbeToReference"
    image: str = "Image_Reference"
    image_pose: str = "embedded"  # "embedded" (IMAGE matrix is ImageToReference) | "calibration"
    image_to_probe: np.ndarray = field(default_factory=_default_image_to_probe)  # 4×4, pixel → mm
    stale_s: float = 0.2
    missing_s: float = 1.0
    rate_hz: float = 10.0
    reconnect_s: float = 0.25  # pause between connection attempts
    tools: tuple[ToolDevices, ...] = ()  # tracked data sources' devices (``[tools.<source>]``)
    source: Path | None = None

    def tool(self, source: str) -> ToolDevices | None:
        """``source``'s own devices, or None (its points arrive in Reference)."""
        return next((t for t in self.tools if t.source == source), None)

    def with_address(self, host=None, port=None) -> "TrackingConfig":
        return replace(self, host=host or self.host, port=port or self.port)


_KEYS: dict[str, dict[str, type]] = {  # section → key → type
    "server": {"host": str, "port": int, "reconnect_s": float},
    "devices": {"stylus": str, "probe": str, "image": str, "image_pose": str},
    "calibration": {"image_to_probe": list},
    "watchdog": {"stale_s": float, "missing_s": float},
    "digitiser": {"rate_hz": float},
    "tools": {},  # one table per tracked data source: ``_tools``
}
_TOOL_KEYS: dict[str, type] = {"pose": str}
_TRACKABLE = tuple(dict.fromkeys(f.source for f in TABLE if f.name in SOURCED))  # sources sending POINT messages


def _tools(table: dict, path) -> tuple[ToolDevices, ...]:
    out = []
    for source, keys in table.items():
        if source not in _TRACKABLE:
            raise InputError(f"unknown tool [tools.{source}] (known: {', '.join(_TRACKABLE) or 'none'})", path)
        if not isinstance(keys, dict):
            raise InputError(f"[tools.{source}] must be a table", path)
        for key, value in keys.items():
            if key not in _TOOL_KEYS:
                raise InputError(f"unknown key tools.{source}.{key} (known: {', '.join(_TOOL_KEYS)})", path)
            _typed(value, _TOOL_KEYS[key], f"tools.{source}.{key}", path)
        if "pose" not in keys:
            raise InputError(f"tools.{source}.pose is missing (the TRANSFORM that places its points)", path)
        out.append(ToolDevices(source, keys["pose"]))
    return tuple(out)


def _typed(value, kind, key, path):
    if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, kind) and not isinstance(value, bool):
        return value
    raise InputError(f"{key} must be a {kind.__name__}, got {value!r}", path)


def parse_config(data: dict, path=None) -> TrackingConfig:
    values: dict[str, Any] = {}
    for section, table in data.items():
        if section not in _KEYS:
            raise InputError(f"unknown section [{section}] (known: {', '.join(_KEYS)})", path)
        if not isinstance(table, dict):
            raise InputError(f"[{section}] must be a table", path)
        if section == "tools":
            values["tools"] = _tools(table, path)
            continue
        for key, value in table.items():
            if key not in _KEYS[section]:
                raise InputError(f"unknown key {section}.{key} (known: {', '.join(_KEYS[section])})", path)
            values[key] = _typed(value, _KEYS[section][key], f"{section}.{key}", path)
    if "image_to_probe" in values:
        try:
            m = np.array(values["image_to_probe"], float)
        except (TypeError, ValueError):
            m = None
        if m is None or m.shape != (4, 4) or not np.isfinite(m).all() or not np.allclose(m[3], [0, 0, 0, 1]):
            raise InputError("calibration.image_to_probe must be a 4×4 matrix (rows) with last row 0 0 0 1", path)
        values["image_to_probe"] = m
    cfg = TrackingConfig(**values, source=Path(path) if path else None)
    if not 0 < cfg.port < 65536:
        raise InputError(f"server.port must be 1–65535, got {cfg.port}", path)
    if cfg.image_pose not in ("embedded", "calibration"):
        raise InputError(f"devices.image_pose must be \"embedded\" or \"calibration\", got {cfg.image_pose!r}", path)
    for name in ("stylus", "probe", "image"):
        v = getattr(cfg, name)
        if not v or len(v.encode()) > 20:
            raise InputError(f"devices.{name} must be 1–20 bytes (an OpenIGTLink device name), got {v!r}", path)
    for t in cfg.tools:
        if not t.pose or len(t.pose.encode()) > 20:
            raise InputError(f"tools.{t.source}.pose must be 1–20 bytes (an OpenIGTLink device name), got {t.pose!r}",
                             path)
        taken = {cfg.stylus, cfg.probe, cfg.image, *SOURCED} | {o.pose for o in cfg.tools if o is not t}
        if t.pose in taken:
            raise InputError(f"tools.{t.source}.pose {t.pose!r} is another device's name", path)
    if not 0 < cfg.stale_s < cfg.missing_s:
        raise InputError("watchdog: need 0 < stale_s < missing_s", path)
    if cfg.rate_hz <= 0 or cfg.reconnect_s <= 0:
        raise InputError("digitiser.rate_hz and server.reconnect_s must be positive", path)
    return cfg


def load_config(path) -> TrackingConfig:
    """Read a tracking TOML file; every problem is one line naming the file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise InputError("no such tracking config file", path) from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"invalid TOML ({exc})", path) from None
    return parse_config(data, path)


def config_fields() -> list[str]:
    return [f.name for f in fields(TrackingConfig)]
