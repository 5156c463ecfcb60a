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

This module reads what the connection, the watchdog and the digitiser share (``[server]``,
``[watchdog]``, ``[digitiser]``); each tool's own settings live with its receiver
(``receivers/<source>.py``: a settings dataclass, its ``KEYS``/``TABLES`` and ``parse``),
found from ``features.TABLE`` (``receivers.modules``): a new kind of tool adds no line here.

A bad file ends in one line naming the file and the key (``InputError``).
"""

import tomllib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TypeVar

from ..errors import InputError
from ..features import SOURCED
from . import receivers
from .receivers.base import ToolSettings, typed

DEFAULT_PORT = 18944  # OpenIGTLink's registered port, PLUS's and Slicer's default
S = TypeVar("S")


@dataclass(frozen=True)
class TrackingConfig:
    """The connection, the watchdog, the digitiser and each tool's own settings.

    ``tools``: the settings of the tools given (``receivers.stylus.StylusSettings``,
    ``receivers.ius.ProbeSettings``, ``receivers.points.PointsSettings``, …); every other
    received source takes its defaults, so ``tools`` ends holding one per received source,
    in ``features.TABLE``'s order. ``tool(source, kind)`` reads one.
    """

    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    stale_s: float = 0.2
    missing_s: float = 1.0
    rate_hz: float = 10.0
    reconnect_s: float = 0.25  # pause between connection attempts
    tools: tuple[ToolSettings, ...] = ()
    source: Path | None = None

    def __post_init__(self):
        given = {t.source: t for t in self.tools}
        known = receivers.defaults()
        unknown = set(given) - {t.source for t in known}
        if unknown:
            raise ValueError(f"no receiver for {', '.join(sorted(unknown))}")
        object.__setattr__(self, "tools", tuple(given.get(t.source, t) for t in known))

    def tool(self, source: str, kind: type[S]) -> S:
        """``source``'s settings, a ``kind`` (its receiver module's settings dataclass)."""
        for t in self.tools:
            if t.source == source:
                if not isinstance(t, kind):
                    raise TypeError(f"{source}'s settings are a {type(t).__name__}, not a {kind.__name__}")
                return t
        raise KeyError(f"no receiver for source {source!r}")

    def with_address(self, host=None, port=None) -> "TrackingConfig":
        return replace(self, host=host or self.host, port=port or self.port)


_KEYS: dict[str, dict[str, type]] = {  # section → key → type, the shared ones (each tool's: its module's KEYS)
    "server": {"host": str, "port": int, "reconnect_s": float},
    "watchdog": {"stale_s": float, "missing_s": float},
    "digitiser": {"rate_hz": float},
}


def _sections() -> tuple[dict[str, dict[str, type]], tuple[str, ...]]:
    """Every key the file may hold (section → key → type) and the sections a tool reads whole."""
    keys: dict[str, dict[str, type]] = {"server": dict(_KEYS["server"])}
    tables: list[str] = []
    for module in dict.fromkeys(receivers.modules().values()):
        for section, own in module.KEYS.items():
            keys.setdefault(section, {}).update(own)
        tables += [t for t in module.TABLES if t not in tables]
    for section in ("watchdog", "digitiser"):
        keys[section] = dict(_KEYS[section])
    return keys, tuple(tables)


def parse_config(data: dict, path=None) -> TrackingConfig:
    keys, tables = _sections()
    values: dict[str, Any] = {}
    for section, table in data.items():
        if section not in keys and section not in tables:
            raise InputError(f"unknown section [{section}] (known: {', '.join([*keys, *tables])})", path)
        if not isinstance(table, dict):
            raise InputError(f"[{section}] must be a table", path)
        if section in tables:
            continue
        for key, value in table.items():
            if key not in keys[section]:
                raise InputError(f"unknown key {section}.{key} (known: {', '.join(keys[section])})", path)
            typed_value = typed(value, keys[section][key], f"{section}.{key}", path)
            if key in _KEYS.get(section, {}):
                values[key] = typed_value
    tools = tuple(m.parse(source, data, path) for source, m in receivers.modules().items())
    seen: set[str] = set(SOURCED)  # a source's POINT devices are named as its features
    for key, name in (n for t in tools for n in t.named):
        if name in seen:
            raise InputError(f"{key} {name!r} is another device's name", path)
        seen.add(name)
    cfg = TrackingConfig(**values, tools=tools, source=Path(path) if path else None)
    if not 0 < cfg.port < 65536:
        raise InputError(f"server.port must be 1–65535, got {cfg.port}", path)
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

