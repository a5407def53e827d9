"""User-facing errors.

Every mistake a user can make (a bad file, a bad config, an unknown parameter) raises
:class:`FricjaxError` with a one-line message naming the file, the field and what is wrong.
The CLI prints that line and exits non-zero; it never shows a traceback for these.
"""

from __future__ import annotations


class FricjaxError(ValueError):
    """A user mistake, described in one line (file, field, what is wrong)."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))


def where(path: object, field: str | None = None) -> str:
    """Format the ``file: field`` prefix of an error message."""
    text = str(path) if path else "<memory>"
    return f"{text}: {field}" if field else text
