"""Models: coordinates, parameters and an energy linear in them; the safe expression
parser; Rayleigh's dissipation function; Lagrange's equations (dynamics).

The innermost step: imports nothing of hamid but `hamid.errors`."""
