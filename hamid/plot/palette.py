"""The figures' colours, shared by every drawing module of `hamid.plot`."""

from __future__ import annotations

__all__ = ["OKABE_ITO", "colour"]

# Okabe & Ito's colour-blind-safe palette (yellow left out: it vanishes on white).
OKABE_ITO = ("#0072B2", "#E69F00", "#009E73", "#D55E00", "#CC79A7", "#56B4E9", "#000000")


def colour(k: int) -> str:
    """The k-th colour of the palette, round again after the last."""
    return OKABE_ITO[k % len(OKABE_ITO)]
