"""The one base class of every error a user can cause and fix (bad scenario, bad value, a
vehicle that never answers...). The command line prints its message as one line and exits
non-zero; anything else is a bug and keeps its traceback."""


class UserError(Exception):
    """A problem in the user's input or environment; the message names it and the fix."""
