"""Value types for the command lines' arguments (argparse ``type=``): one home, used by
``navapp.cli`` and every sub-command's parser."""

import argparse
import math

K_MAX = 1000  # control points: the paper uses 45, the cost study at most 90; 3k modes per node beyond this


def positive(kind, most=None, least=None):
    """A parser of finite numbers of ``kind`` (int or float) > 0 (or ≥ ``least``), at most
    ``most``, with a one-line error."""
    def parse(s):
        try:
            v = kind(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {s!r}") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"must be a finite number: {s!r}")
        if (v < least) if least is not None else (v <= 0):
            raise argparse.ArgumentTypeError(f"must be {'positive' if least is None else f'>= {least}'}: {s!r}")
        if most is not None and v > most:
            raise argparse.ArgumentTypeError(f"must be at most {most}: {s!r}")
        return v
    return parse


k_count = positive(int, most=K_MAX)


def address(s: str) -> str:
    """A scheduler address: not empty (``--scheduler ""`` was taken as no scheduler, silently)."""
    if not s.strip():
        raise argparse.ArgumentTypeError("an empty address; give host:port, or leave --scheduler out")
    return s.strip()
