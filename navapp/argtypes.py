"""Value types for the command lines' arguments (argparse ``type=``): one home, used by
``navapp.cli`` and every sub-command's parser."""

import argparse


def positive(kind):
    """A parser of positive numbers of ``kind`` (int or float) with a one-line error."""
    def parse(s):
        try:
            v = kind(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {s!r}") from None
        if v <= 0:
            raise argparse.ArgumentTypeError(f"must be positive: {s!r}")
        return v
    return parse
