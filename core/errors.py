"""Error types that map to the CLI's exit codes (2 for user errors, 1 for bugs)."""

from __future__ import annotations


class UserError(Exception):
    """A problem the user can fix: bad input file, unknown parameter, missing topic, held lock.

    The message is one line that names the file, topic or parameter and says what to do.
    """


class LockHeldError(UserError):
    """Another process holds the per-sequence lock."""
