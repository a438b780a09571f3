"""Text shown safely and plainly: every control character of text from data files that a
terminal would obey (escape sequences, bidirectional overrides) written as a visible escape
instead; a count with its noun in agreement ("1 trajectory", "2 trajectories")."""

from __future__ import annotations

import functools
import re

__all__ = ["counted", "printable"]

# What a terminal obeys instead of showing: C0 controls (ESC starts the sequences that set the
# window title, move the cursor or hide text), DEL, C1 controls (U+009B is a one-character
# CSI), line and paragraph separators, and the bidirectional marks and overrides that reorder
# what is shown ("Trojan source").
_CONTROLS = "\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u2028\u2029\u202a-\u202e\u2066-\u2069"
_NAMED_ESCAPES = {"\n": "\\n", "\r": "\\r", "\t": "\\t"}


def printable(text: str, *, keep: str = "") -> str:
    """`text` with every control character a terminal would obey shown as an escape instead.

    Names, labels and messages that come from data files are escaped before they are shown:
    ESC becomes the four characters ``\\x1b``, U+009B ``\\x9b``, U+202E ``\\u202e``, a newline
    ``\\n``. Other text, accents and symbols included, is left alone.

    Parameters
    ----------
    text : str
        Text to show.
    keep : str, optional
        Control characters to leave as they are, such as the newlines and tabs of a table.

    Examples
    --------
    >>> printable("x\\x1b]0;owned\\x07")
    'x\\\\x1b]0;owned\\\\x07'
    """
    return _controls(keep).sub(_escape_control, text)


@functools.lru_cache(maxsize=8)
def _controls(keep: str) -> re.Pattern[str]:
    """Helper: the pattern of the control characters to escape, less those kept."""
    if not keep:
        return re.compile(f"[{_CONTROLS}]")
    return re.compile(f"(?![{re.escape(keep)}])[{_CONTROLS}]")


def _escape_control(match: re.Match[str]) -> str:
    """Helper: the visible escape of one control character."""
    char = match.group()
    named = _NAMED_ESCAPES.get(char)
    if named is not None:
        return named
    return f"\\x{ord(char):02x}" if ord(char) < 0x100 else f"\\u{ord(char):04x}"


def counted(n: float, one: str, many: str) -> str:
    """`n` with its noun in agreement: `one` for exactly 1, `many` otherwise; a whole float
    without its decimal point.

    Examples
    --------
    >>> counted(1, "trajectory", "trajectories"), counted(2.0, "segment", "segments")
    ('1 trajectory', '2 segments')
    """
    shown = int(n) if float(n).is_integer() else n
    return f"{shown} {one if n == 1 else many}"
