"""Errors a user can act on. The CLI prints them as one line, never a traceback."""


class NavappError(Exception):
    """Base class: a problem with the user's input or environment, stated in one line."""


class InputError(NavappError):
    """Bad input file or argument. ``path`` names the file when there is one."""

    def __init__(self, message: str, path=None):
        self.path = None if path is None else str(path)
        super().__init__(f"{self.path}: {message}" if self.path else message)
