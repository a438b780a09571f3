"""The names of a model's variables that follow from others: the accelerations' defaults,
beside the velocities' names. No numpy: the column roles use them."""

from __future__ import annotations

__all__ = ["acceleration_name"]

_RATES = (("omega", "alpha"), ("v", "a"))


def acceleration_name(velocity: str) -> str:
    """The default name of the acceleration beside a velocity: v -> a, v1 -> a1, vx -> ax,
    omega -> alpha, x_dot -> x_ddot, xdot -> xddot, dx -> ddx (else the velocity's name
    with ``_dot``).

    Examples
    --------
    >>> [acceleration_name(v) for v in ("v", "vx", "omega2", "x_dot", "dx", "p")]
    ['a', 'ax', 'alpha2', 'x_ddot', 'ddx', 'p_dot']
    """
    for rate, acceleration in _RATES:
        if velocity.startswith(rate):
            return acceleration + velocity[len(rate):]
    if velocity.endswith("dot"):
        return velocity[:-3] + "ddot"
    return "d" + velocity if velocity.startswith("d") else velocity + "_dot"
