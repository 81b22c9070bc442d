"""The exception every user-caused failure derives from.

The command line prints the message of a :class:`SoftgripError` without a traceback; anything else is
a bug and keeps its traceback. Messages name the input at fault and say what to do about it.
"""


class SoftgripError(ValueError):
    """A failure caused by the user's input (a file, a setting, a parameter), not by a bug."""
