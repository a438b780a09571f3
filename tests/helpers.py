"""Helpers shared by test modules (pytest puts this folder on the import path)."""

from __future__ import annotations

import ast
import builtins
import os
import select
import sys
from pathlib import Path
from unittest import mock


class Readiness:
    """A pipe on which a child process says that the work a test waits for has begun.

    The child runs `announcing(...)`'s code before hamid's command line, so the byte comes
    from inside that work, after hamid installed its signal handlers: a signal sent then
    meets them however busy the machine is, and no test guesses with a clock. Pass `fd` to
    the child (`pass_fds`), then `wait()`.
    """

    def __init__(self) -> None:
        self._read_end, self.fd = os.pipe()

    def __enter__(self) -> Readiness:
        return self

    def __exit__(self, *exc: object) -> None:
        for fd in (self._read_end, self.fd):
            if fd >= 0:
                os.close(fd)
        self._read_end = self.fd = -1

    def announcing(self, target: str, *, call: int = 1, hold: bool = False) -> str:
        """Python code that wraps `target` ("module.function") to write the byte on its
        `call`-th call, then, with `hold`, to sleep until a signal ends the process."""
        module, name = target.rsplit(".", 1)
        held = "        time.sleep(3600)\n" if hold else ""
        return (f"import importlib, itertools, os, time\n"
                f"_owner = importlib.import_module({module!r})\n"
                f"_original, _calls = _owner.{name}, itertools.count(1)\n"
                f"def _announced(*args, **kwargs):\n"
                f"    if next(_calls) == {call}:\n"
                f"        os.write({self.fd}, b'r')\n"
                f"{held}"
                f"    return _original(*args, **kwargs)\n"
                f"_owner.{name} = _announced\n")

    def wait(self, timeout: float = 600.0) -> None:
        """Block until the child has announced; fail, never go on, if it ended first or
        hangs (the timeout only bounds a hang)."""
        os.close(self.fd)   # the child holds its copy: end of file now means it has gone
        self.fd = -1
        ready, _, _ = select.select([self._read_end], [], [], timeout)
        assert ready, f"the process was not ready after {timeout:.0f} s"
        assert os.read(self._read_end, 1) == b"r", "the process ended before it was ready"


def interrupted(args: list[str], target: str, *, call: int = 1,
                hold: bool = False) -> tuple[int, str, str]:
    """Run hamid with `args` and press Ctrl-C (SIGINT) once the child announces `target`
    (`Readiness.announcing`), as at a terminal: SIGINT at its default even when the test
    runs in the background, which ignores it. The exit status, stdout and stderr."""
    import signal
    import subprocess

    with Readiness() as readiness:
        command = hamid_command(before=readiness.announcing(target, call=call, hold=hold))
        process = subprocess.Popen(
            [*command, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            pass_fds=(readiness.fd,),
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        try:
            readiness.wait()
            process.send_signal(signal.SIGINT)
            stdout, stderr = process.communicate(timeout=600)
        finally:
            if process.poll() is None:
                process.kill()
                process.communicate()
    return process.returncode, stdout, stderr


def hamid_command(before: str = "") -> list[str]:
    """The command that runs hamid's CLI in a subprocess, after the Python code `before`:
    this interpreter and the working tree (first on the children's PYTHONPATH,
    tests/conftest.py), never a `hamid` script found on PATH, which may belong to another
    copy."""
    return [sys.executable, "-c", f"{before}from hamid.cli import main; main()"]


def duffing_system(*, k: str = "1.0", k3: str = "0.5", x: str = "1.0", v: str = "0.0",
                   t_end: str = "2.0", dt: str = "0.1") -> str:
    """A one-trajectory Duffing system file, each value written as given."""
    return (f'[model]\nbuiltin = "duffing"\n\n[parameters]\nk = {k}\nk3 = {k3}\n\n'
            f'[[initial]]\nx = {x}\nv = {v}\n\n[simulate]\nt_end = {t_end}\ndt = {dt}\n')


def one_line_error(done, code: int, *words: str) -> str:
    """A clean failure of a subprocess or a CliRunner result, its stderr in bytes or text:
    the exit status `code`, nothing on standard output (where captured), and one line on
    standard error, no traceback or internal error, naming every one of `words`."""
    exit_code = getattr(done, "returncode", getattr(done, "exit_code", None))
    stderr = done.stderr.decode() if isinstance(done.stderr, bytes) else done.stderr
    stdout = done.stdout.decode() if isinstance(done.stdout, bytes) else done.stdout
    assert exit_code == code, (exit_code, stderr)
    assert stdout in (None, ""), stdout
    assert "Traceback" not in stderr and "internal error" not in stderr, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("Error: "), stderr
    for word in words:
        assert word in lines[0], (word, stderr)
    return lines[0]


def snapshot(folder) -> dict:
    """Every entry of a folder: symlinks with their targets, files with their bytes, and
    the kind of anything else; what a refused command must leave as it was."""
    import stat

    entries = {}
    for entry in sorted(os.listdir(folder)):
        path = Path(folder) / entry
        mode = os.lstat(path).st_mode
        if stat.S_ISLNK(mode):
            entries[entry] = ("link", os.readlink(path))
        elif stat.S_ISREG(mode):
            entries[entry] = ("file", path.read_bytes())
        else:
            entries[entry] = ("other", stat.S_IFMT(mode))
    return entries


def double_pendulum_rhs(g: float):
    """The double pendulum of unit masses and lengths, its equations written out by hand
    (solve_ivp's right-hand side over (p, q, wp, wq)): a truth independent of hamid's."""
    import numpy as np

    def rhs(t, y):
        p, q, wp, wq = y
        s, c, den = np.sin(p - q), np.cos(p - q), 3 - np.cos(2 * (p - q))
        return [wp, wq,
                (-3 * g * np.sin(p) - g * np.sin(p - 2 * q) - 2 * s * (wq**2 + wp**2 * c)) / den,
                2 * s * (2 * wp**2 + 2 * g * np.cos(p) + wq**2 * c) / den]
    return rhs


def two_dof_first_mode(amplitudes, k1: float, k2: float, k3: float,
                       c1: float = 0.0, c2: float = 0.0) -> list[tuple[float, float]]:
    """The first nonlinear normal mode of x1'' = -k1 x1 + k2 (x2 - x1) - k3 x1^3,
    x2'' = -k2 (x2 - x1) (unit masses), by a shooting of its own: at each amplitude A of
    x1, its frequency (rad/s) and, for viscous dampers c1, c2 on the two coordinates, its
    equivalent damping ratio ΔE / (4π E), ΔE integrated alongside the conservative orbit.
    The orbit starts at rest from (A, b) and, the potential being even, reaches (-A, -b)
    at half its period T. A truth independent of hamid's."""
    import math

    import numpy as np
    from scipy.integrate import solve_ivp
    from scipy.optimize import root

    def rhs(t, y):
        x1, x2, v1, v2, _ = y
        return [v1, v2, -k1 * x1 + k2 * (x2 - x1) - k3 * x1 ** 3, -k2 * (x2 - x1),
                c1 * v1 ** 2 + c2 * v2 ** 2]

    def half(b, T, A):
        return solve_ivp(rhs, (0, T / 2), [A, b, 0, 0, 0], method="DOP853", rtol=1e-12,
                         atol=1e-13).y[:, -1]

    # the linear mode as the first guess: x2 = x1 k2 / (k2 - w^2), from K phi = w^2 phi
    trace, det = k1 + 2 * k2, k1 * k2
    w2 = (trace - math.sqrt(trace ** 2 - 4 * det)) / 2
    guess = np.array([k2 / (k2 - w2), 2 * math.pi / math.sqrt(w2)])
    found = []
    for A in amplitudes:
        guess = root(lambda u, A=A: [half(*u, A)[0] + A, half(*u, A)[1] + u[0]],
                     guess * [A if not found else 1, 1], tol=1e-13).x
        b, T = guess
        energy = k1 * A ** 2 / 2 + k2 * (b - A) ** 2 / 2 + k3 * A ** 4 / 4
        lost = 2 * half(b, T, A)[4]   # the second half retraces the first
        found.append((2 * math.pi / T, lost / (4 * math.pi * energy)))
    return found


def velocity_findings(frame, coordinates: tuple[str, ...], velocities: tuple[str, ...]):
    """`measurement.velocity_check` of a frame of trajectories (a `trajectory` column, `t`),
    at the dominant period of its positions."""
    import numpy as np

    from hamid.data.measurement import velocity_check
    from hamid.data.records import Records
    from hamid.linear import design

    groups = frame["trajectory"].to_numpy() - frame["trajectory"].min()
    records = Records(frame[[*coordinates, *velocities]].to_numpy(), frame["t"].to_numpy(),
                      groups, tuple(np.unique(groups)))
    period = design.median_period(design.trajectory_scales(records, len(coordinates)))
    return velocity_check(records, coordinates, velocities, {}, period)


# The syntax-tree nodes a parsed expression may hold: numbers, names, calls, + - * / **
SAFE_NODES = (ast.BinOp, ast.UnaryOp, ast.Call, ast.Name, ast.Constant, ast.Load, ast.Add,
              ast.Sub, ast.Mult, ast.Div, ast.Pow, ast.USub, ast.UAdd)


def parsed_running_nothing(text: str, names: list[str]) -> ast.expr | None:
    """hamid's parse of `text` (None when it is refused), asserting that parsing ran
    nothing: no shell command, eval or exec."""
    from hamid.errors import ModelError
    from hamid.model.parsing import parse

    calls: list[tuple] = []
    with mock.patch.object(os, "system", lambda *a: calls.append(a) or 0), \
            mock.patch.object(builtins, "eval", lambda *a, **k: calls.append(a)), \
            mock.patch.object(builtins, "exec", lambda *a, **k: calls.append(a)):
        try:
            tree = parse(text, names)
        except ModelError:
            tree = None
    assert calls == [], text
    return tree
