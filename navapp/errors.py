"""Errors a user can act on. The CLI prints them as one line, never a traceback."""


class NavappError(Exception):
    """Base class: a problem with the user's input or environment, stated in one line."""


class InputError(NavappError):
    """Bad input file or argument. ``path`` names the file when there is one."""

    def __init__(self, message: str, path=None):
        self.path = None if path is None else str(path)
        super().__init__(f"{self.path}: {message}" if self.path else message)


class CarriedWarning(UserWarning):
    """A warning that the registration also carries among its own warnings
    (``Registration.warnings``): the command line prints those once, with the case's name,
    and so ignores this Python warning, which a library caller still sees."""


def short_error(exc: Exception) -> str:
    """A reader's exception as a short phrase for a one-line error (its first line, at most
    80 characters)."""
    lines = str(exc).strip().splitlines()
    text = lines[0] if lines else type(exc).__name__
    return text if len(text) <= 80 else text[:79] + "…"
