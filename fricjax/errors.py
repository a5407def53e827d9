"""User-facing errors.

Every mistake a user can make (a bad file, a bad config, an unknown parameter) raises
:class:`FricjaxError` with a one-line message naming the file, the field and what is wrong.
The CLI prints that line and exits non-zero; it never shows a traceback for these.
"""

from __future__ import annotations

#: Exit statuses of the ``fricjax`` command (documented in docs/robustness.md): a script
#: tells a usable partial result (3) from nothing written (130) and from a refusal.
EXIT = {
    "ok": 0,
    "machine": 1,  # the machine refused an output: disk full, folder not writable
    "mistake": 2,  # the user's mistake: command line, input file, config
    "partial": 3,  # Ctrl-C after partial results were written (they say interrupted)
    "interrupted": 130,  # Ctrl-C before anything was written (128 + SIGINT)
}


class FricjaxError(ValueError):
    """A user mistake, described in one line (file, field, what is wrong)."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))


def where(path: object, field: str | None = None) -> str:
    """Format the ``file: field`` prefix of an error message."""
    text = str(path) if path else "<memory>"
    return f"{text}: {field}" if field else text


class OutputFault(OSError):
    """The machine refused to store an output (disk full, read-only folder), in one line.

    Not the user's mistake in the command (exit 1, not 2); the earlier file at that path,
    if any, is left as it was.
    """

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))

    def __str__(self) -> str:
        return str(self.args[0])
