"""Guards and their resets: where a hybrid system jumps, and to what.

A :class:`Guard` is a named surface ``psi(s) = 0`` that fires when ``psi`` crosses zero from
above, with its reset map ``s+ = g(s-)``; a :class:`~hybridoc.ocp.HybridOCP` holds a list of
them. A guard of a problem with modes also names its ``source`` and ``target`` mode
(:mod:`hybridoc.modes`).

Resets that depend on the control
    A guard's reset may be ``s+ = g(s-, u)`` (:meth:`Guard.from_expressions` with ``u=``;
    :attr:`Guard.uses_control`): a restitution or an impulse the controller sets at the
    impact. On the N-grid (the judge of piecewise-constant controls, gradient descent) the
    reset reads the control of the grid cell in which the event happens, and the judge's
    adjoint adds ``lambda(gamma+)^T dg/du`` to that cell's gradient. In continuous time
    (the transcription, the reference) the reset's control at each event is a decision of
    its own, ``v_k`` in the control bounds: a single instant carries no running cost, so
    ``v_k`` minimises ``lambda(gamma+)^T g(s(gamma-), v)`` (a linear dependence needs bounds
    for a minimum to exist). Such a Solution stores the ``v_k``
    (``arrays["event_controls"]``) and the judge
    applies them at its events. The transcription and the HMP reference (where ``v_k`` are
    shooting unknowns with their own stationarity condition) solve these problems.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import casadi as ca

from hybridoc.errors import SceneError

__all__ = ["Guard", "casadi_name"]


@dataclass(frozen=True)
class Guard:
    """A named guard ``psi(s) = 0`` with its reset map ``s+ = g(s-)``.

    Parameters
    ----------
    name
        Unique name, e.g. ``"ball1|ball2"``.
    psi
        CasADi Function ``s -> scalar``; positive in free space.
    reset
        CasADi Function ``s -> s``, or ``(s, u) -> s`` for a reset that depends on the
        control (:attr:`uses_control`; module notes, "Resets that depend on the control").
    kind
        Free label reported with events, e.g. ``"disc-disc"``.
    bodies
        Names of the bodies involved, reported with events.
    detector
        Optional CasADi Function ``s -> scalar`` with the same sign and zero set as ``psi``
        that is polynomial along the flow (e.g. a squared distance). Used only to locate
        events; defaults to ``psi``.
    degree
        Degree in time of ``detector`` along the flow under a constant control, if it is a
        polynomial (then events are located exactly from ``degree + 1`` samples per grid
        interval); ``None`` for a general smooth guard. For a transition between modes: along
        the flow of its source mode.
    source, target
        For a transition of a problem with modes (:meth:`HybridOCP.from_modes
        <hybridoc.ocp.HybridOCP.from_modes>`): the mode in which the guard can fire and the
        mode its reset enters; ``None`` for problems without modes.
    """

    name: str
    psi: ca.Function
    reset: ca.Function
    kind: str = "event"
    bodies: tuple[str, ...] = ()
    detector: ca.Function | None = None
    degree: int | None = None
    source: str | None = None
    target: str | None = None

    def __post_init__(self) -> None:
        r = self.reset
        if not isinstance(r, ca.Function) or r.n_in() not in (1, 2) or r.n_out() != 1:
            got = f"{r.n_in()} inputs" if isinstance(r, ca.Function) else type(r).__name__
            raise SceneError(
                f"guard {self.name!r}: the reset must be a casadi.Function s -> s or "
                f"(s, u) -> s, got {got}"
            )

    @property
    def uses_control(self) -> bool:
        """Whether the reset is a function of the state and the control, ``(s, u) -> s``."""
        return int(self.reset.n_in()) == 2

    def reset_at(self, s: Any, u: Any) -> Any:
        """The state after the jump, ``g(s)`` or ``g(s, u)``, for symbols or numbers
        (``u`` is read only by a reset that :attr:`uses_control`)."""
        return self.reset(s, u) if self.uses_control else self.reset(s)

    def check_reset(self, nx: int, nu: int, *, what: str | None = None) -> None:
        """Raise a :class:`~hybridoc.errors.SceneError` naming the expected signature unless
        the reset is ``s -> s`` or ``(s, u) -> s`` with ``s`` of size ``nx`` and ``u`` of
        size ``nu``."""
        r = self.reset
        sizes = tuple(r.size_in(i) for i in range(r.n_in()))
        want = ((nx, 1),) if r.n_in() == 1 else ((nx, 1), (nu, 1))
        if sizes != want or r.size_out(0) != (nx, 1):
            shown = ", ".join(f"{a}x{b}" for a, b in sizes)
            out = "x".join(map(str, r.size_out(0)))
            raise SceneError(
                f"{what or f'guard {self.name!r}'}: the reset must be a Function s -> s or "
                f"(s, u) -> s with s of size {nx} and u of size {nu} (a reset that depends on "
                f"the control takes the state first), got inputs ({shown}) -> {out}"
            )

    @classmethod
    def from_expressions(
        cls,
        name: str,
        s: ca.SX | ca.MX,
        psi: ca.SX | ca.MX,
        reset: ca.SX | ca.MX,
        *,
        kind: str = "event",
        bodies: Sequence[str] = (),
        detector: ca.SX | ca.MX | None = None,
        degree: int | None = None,
        source: str | None = None,
        target: str | None = None,
        u: ca.SX | ca.MX | None = None,
    ) -> Guard:
        """Build a guard from symbolic expressions in the state symbol ``s``.

        ``reset`` may also use the control symbol ``u`` when it is given: the reset is then
        ``(s, u) -> s`` (module notes, "Resets that depend on the control"); a reset that
        does not use ``u`` stays ``s -> s``.
        """
        tag = casadi_name(name)
        det = None if detector is None else ca.Function(f"det_{tag}", [s], [detector])
        with_u = u is not None and isinstance(reset, ca.SX | ca.MX) and ca.depends_on(reset, u)
        try:
            g = (
                ca.Function(f"g_{tag}", [s, u], [reset])
                if with_u
                else ca.Function(f"g_{tag}", [s], [reset])
            )
        except RuntimeError as exc:
            # CasADi's last line names the free symbols ("variables [u] are free")
            free = re.search(r"variables \[(.*?)\] are free", str(exc))
            which = f"it uses {free.group(1)}" if free else str(exc).splitlines()[-1]
            hint = "" if u is not None else " (pass u= for a reset that depends on the control)"
            raise SceneError(
                f"guard {name!r}: the reset must be an expression in s, or in s and u{hint}; "
                f"{which}"
            ) from None
        return cls(
            name=name,
            psi=ca.Function(f"psi_{tag}", [s], [psi]),
            reset=g,
            kind=kind,
            bodies=tuple(bodies),
            detector=det,
            degree=degree,
            source=source,
            target=target,
        )


def casadi_name(name: str) -> str:
    """A valid CasADi function-name suffix derived from any guard name."""
    # ASCII only: str.isalnum accepts letters such as "\u00e9", which CasADi rejects
    out = "".join(ch if ch.isascii() and ch.isalnum() else "_" for ch in name)
    while "__" in out:
        out = out.replace("__", "_")
    return out.strip("_") or "guard"
