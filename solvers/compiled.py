"""The compiled fast path: one CasADi step iterated by ``mapaccum``, its loss and gradient.

A :class:`CompiledLoss` builds the discrete objective ``phi(s_N) + sum_n c_n`` of a problem
from one step function ``(s, u) -> (s_next, c)``:

* disc scenes: the simulator's step in CasADi (:func:`hybridoc.solvers.casadi_step.make_step`,
  any contact model; symplectic Euler or the exact flow, with the time-of-impact corrections)
  and the running cost ``eps |u|^2 dt``;
* any other problem (or a disc scene with ``simulation="generic"``): the generic
  time-of-impact step of :func:`hybridoc.solvers.toi_sim.toi_step`.

The step is iterated by CasADi's ``mapaccum`` (one small graph, whatever N: set-up time does
not grow with N) and the gradient is the discrete adjoint, a backward ``mapaccum``.
Evaluation runs in CasADi's virtual machine until the same functions compiled to C are ready
(:mod:`hybridoc.solvers.codegen`: in the background, cached on disk, bit for bit the same
numbers); a batch of B controls (and initial states) is one call of the function mapped
over B. Gradient descent (:mod:`hybridoc.solvers.gd`) calls :meth:`CompiledLoss.value_and_grad`
on numpy arrays, with the numpy optimisers of :mod:`hybridoc.solvers.optimizers`: torch is
never imported. :meth:`CompiledLoss.loss` exposes the same function to torch as an autograd
function (imported on first use), so it plugs into torch optimisers and policy training.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np

from hybridoc.errors import ControlsError, SceneError
from hybridoc.problems import scene_of
from hybridoc.solvers.codegen import Accelerated
from hybridoc.solvers.contacts import ContactModel, contact_model

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.ocp import HybridOCP, Structure
    from hybridoc.problem import ProblemLike

__all__ = ["CompiledLoss", "SIMULATIONS", "TerminalLoss", "per_structure", "translated"]

SIMULATIONS = ("auto", "disc", "generic")
"""Which step :class:`CompiledLoss` compiles: ``auto`` (the disc step for disc scenes, the
generic TOI step otherwise), ``disc`` or ``generic``."""


def per_structure(
    store: weakref.WeakKeyDictionary[Structure, dict[tuple[Any, ...], Any]],
    ocp: HybridOCP,
    key: tuple[Any, ...],
    build: Callable[[], Any],
) -> Any:
    """``build()`` once per problem structure and ``key``, kept in ``store`` while the
    structure lives (weakly, per :class:`~hybridoc.ocp.Structure`): building a compiled loss
    takes milliseconds to seconds, and continuation stages, repeated solves and a dataset's
    draws ask for the same one. More than eight keys of one structure (e.g. the initial
    states of many draws) start its entry afresh."""
    cache = store.setdefault(ocp.structure, {})
    value = cache.get(key)
    if value is None:
        if len(cache) > 8:
            cache.clear()
        value = cache[key] = build()
    return value


def _threads() -> int:
    """CasADi map threads (:func:`hybridoc.solvers.threads.casadi_threads`)."""
    from hybridoc.solvers.threads import casadi_threads

    return casadi_threads()


class CompiledLoss:
    """The discrete objective of a problem and its exact gradient, compiled with CasADi.

    Parameters
    ----------
    problem : ProblemLike
        Any problem (:func:`hybridoc.problem.as_ocp`).
    contact : ContactModel, str or None
        Contact model of the disc step: an instance (``LCP(toi="both")``) or a name of any
        registered model (``"lcp"``, ``"lcp/both"``), parsed once by
        :func:`~hybridoc.solvers.contacts.contact_model`; ``None`` is ``"direct"``.
        :func:`hybridoc.solvers.casadi_step.make_step` says which settings and scenes it
        serves. The generic step has no contact model and ignores it.
    integrator : str, optional
        ``"symplectic-euler"`` (the paper's, the default of the disc step) or ``"exact"``;
        the generic step is always ``"exact"`` (the closed-form flow, or RK4 sub-steps).
    toi : str, optional
        Time-of-impact correction of an impulse model (``None``: the model's own), folded
        into the model.
    simulation : str
        See :data:`SIMULATIONS`.
    max_events : int
        Events resolved per step by the generic step.
    path_weight : float
        Problems with path constraints ``c(s, u) >= 0``: the step cost gains
        ``path_weight * dt * |min(c(s_{n+1}, u_n), 0)|^2`` (a quadratic penalty at the grid).

    Attributes
    ----------
    model : ContactModel or None
        The contact model of the disc step (``None`` for the generic step).
    settings : dict
        JSON-ready description of the step.

    Notes
    -----
    The problem's parameters are constants of the compiled graph. Use the torch
    :class:`~hybridoc.solvers.simulator.Simulator` to differentiate with respect to disc radii,
    masses or restitution.
    """

    def __init__(
        self,
        problem: ProblemLike,
        contact: ContactModel | str | None = "direct",
        integrator: str | None = None,
        *,
        toi: str | None = None,
        simulation: str = "auto",
        max_events: int = 2,
        path_weight: float = 1e5,
    ) -> None:
        from hybridoc.problem import as_ocp

        if simulation not in SIMULATIONS:
            raise SceneError(
                f"simulation must be one of {', '.join(SIMULATIONS)}, got {simulation!r}"
            )
        ocp = as_ocp(problem)  # a Scene's to_ocp()
        is_disc = scene_of(ocp) is not None
        # a disc scene far from the origin is simulated moved by its offset (exactly): the
        # same numbers as at the origin, not rounded to the ulp of the far positions
        sim, self._offset = translated(ocp) if is_disc and simulation != "generic" else (ocp, None)
        if simulation == "disc" and not is_disc:
            raise SceneError(f"{ocp.name!r} is not a disc scene: use simulation='generic'")
        use_disc = is_disc and simulation != "generic"
        model = contact_model("direct" if contact is None else contact, toi=toi)
        self.model: ContactModel | None = model if use_disc else None
        self.ocp = ocp
        self.steps = N = ocp.steps
        self.nx = nx = ocp.nx
        self.nu = nu = ocp.nu
        self.simulation = "disc" if use_disc else "generic"
        if use_disc:
            integrator = integrator or "symplectic-euler"
            step_fn = _disc_step(sim, model, integrator)
            self.settings = {**model.settings(), "integrator": integrator}
        else:
            if integrator not in (None, "exact"):
                raise SceneError(
                    f"integrator {integrator!r} applies to disc scenes only; the generic "
                    "time-of-impact simulation integrates the flow exactly (or by RK4)"
                )
            from hybridoc.solvers.toi_sim import toi_step

            step_fn = toi_step(ocp, ocp.dt, max_events=max_events)
            self.settings = {"simulation": "generic", "integrator": "exact"}
        if ocp.path is not None:
            step_fn = _with_path_penalty(ocp, step_fn, path_weight)
        self.step = step_fn
        value, value_grad, self._rollout = _rollout_functions(step_fn, sim.phi, nx, nu, N)
        self._value = Accelerated(value)
        self._value_grad = Accelerated(value_grad)
        self._maps: dict[int, Accelerated] = {}
        self._x0 = sim.x0.copy()
        self.threads = _threads()

    # ------------------------------------------------------------------ numpy interface
    def _check(self, controls: Any) -> np.ndarray:
        from hybridoc.ocp import as_float_array

        u = as_float_array(controls, "controls", error=ControlsError)
        if u.shape != (self.steps, self.nu):
            raise ControlsError(
                f"controls must have shape ({self.steps}, {self.nu}), got {u.shape}"
            )
        if not np.isfinite(u).all():
            raise ControlsError("controls contain NaN or infinite values")
        return u

    def _start(self, x0: Any) -> np.ndarray:
        """The simulation's initial state(s) of ``x0`` (the problem's when ``None``): moved
        by the offset where the simulation is (:func:`translated`)."""
        if x0 is None:
            return self._x0
        x = np.asarray(x0, dtype=float)
        return x if self._offset is None else x - self._offset

    def value(self, controls: Any, x0: Any = None) -> float:
        """The discrete objective of ``(N, nu)`` controls."""
        u = self._check(controls)
        x = self._start(x0)
        (J,) = self._value.call_numpy(x, u.T)
        return float(J[0, 0])

    def value_and_grad(self, controls: Any, x0: Any = None) -> tuple[float, np.ndarray, np.ndarray]:
        """Objective, gradient ``(N, nu)`` w.r.t. the controls and ``(nx,)`` w.r.t. ``x0``."""
        u = self._check(controls)
        x = self._start(x0)
        J, gx, gU = self._value_grad.call_numpy(x, u.T)
        return float(J[0, 0]), gU.T.copy(), gx.ravel()

    def value_and_grad_batch(
        self, controls: np.ndarray, x0: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Objectives ``(B,)`` and gradients ``(B, N, nu)``, ``(B, nx)`` of a batch, in one
        call of the mapped function (CasADi threads, :attr:`threads`)."""
        u = np.asarray(controls, dtype=float)
        B = u.shape[0]
        if u.shape[1:] != (self.steps, self.nu):
            raise ControlsError(
                f"controls must have shape (B, {self.steps}, {self.nu}), got {u.shape}"
            )
        x = np.broadcast_to(self._start(x0), (B, self.nx))
        fn = self._maps.get(B)
        if fn is None:
            vg = self._value_grad.vm
            # CasADi's virtual machine in threads meanwhile; compiled C runs the batch serially
            # (eight times faster per start than the virtual machine)
            threaded = vg.map(B, "thread", self.threads) if self.threads > 1 and B > 1 else None
            fn = Accelerated(vg.map(B), vm=threaded)
            self._maps[B] = fn
        # map concatenates horizontally: x0 (nx, B), U (nu, N B)
        U = u.transpose(2, 0, 1).reshape(self.nu, B * self.steps)
        J, gx, gU = fn.call_numpy(x.T, U)
        J = J.ravel()
        gx = gx.T.copy()
        gU = gU.reshape(self.nu, B, self.steps).transpose(1, 2, 0).copy()
        return J, gU, gx

    def rollout_numpy(self, controls: Any, x0: Any = None) -> np.ndarray:
        """States ``(N + 1, nx)`` of the discrete rollout."""
        u = self._check(controls)
        x = self._start(x0)
        states = np.asarray(self._rollout(x, u.T)).T.copy()
        return states if self._offset is None else states + self._offset

    # ------------------------------------------------------------------ torch interface
    def loss(self, controls: Any, x0: Any = None) -> Any:
        """Differentiable objective: ``(B,)`` for ``(B, N, nu)`` controls, scalar for ``(N, nu)``.

        Gradients flow to ``controls`` and ``x0`` (``(nx,)`` or ``(B, nx)``).
        """
        import torch

        u = torch.as_tensor(controls)
        batched = u.ndim == 3
        if u.ndim == 2:
            u = u.unsqueeze(0)
        if u.ndim != 3 or tuple(u.shape[1:]) != (self.steps, self.nu):
            raise ControlsError(
                f"controls must have shape ({self.steps}, {self.nu}) or "
                f"(B, {self.steps}, {self.nu}), got {tuple(torch.as_tensor(controls).shape)}"
            )
        if x0 is None:
            x0 = torch.as_tensor(self._x0, dtype=u.dtype, device=u.device)
        else:
            x0 = torch.as_tensor(x0, dtype=u.dtype, device=u.device)
            if self._offset is not None:  # the simulation's coordinates (translated)
                x0 = x0 - torch.as_tensor(self._offset, dtype=u.dtype, device=u.device)
        x0 = x0.expand(u.shape[0], self.nx) if x0.ndim == 1 else x0
        out = _loss_function().apply(u, x0, self)
        return out if batched else out[0]

    def rollout(self, controls: Any, x0: Any = None) -> Any:
        """States ``(B, N + 1, nx)`` (no gradient; use the torch simulator for that)."""
        import torch

        u = torch.as_tensor(controls)
        if u.ndim == 2:
            u = u.unsqueeze(0)
        x = None if x0 is None else torch.as_tensor(x0).detach().cpu().numpy()
        xs = [
            self.rollout_numpy(u[b].detach().cpu().numpy(), x if x is None or x.ndim == 1 else x[b])
            for b in range(u.shape[0])
        ]
        return torch.as_tensor(np.stack(xs), dtype=u.dtype, device=u.device)


def translated(ocp: HybridOCP) -> tuple[HybridOCP, np.ndarray | None]:
    """A disc problem moved by its position offset (:attr:`~hybridoc.scales.Scales.state_offset`)
    to near the origin, with that offset ``(nx,)``; ``(ocp, None)`` where it has none.

    The dynamics, contacts and cost of a disc scene do not change when every position,
    target and wall point moves by the same vector, and the offset (a multiple of 1024
    lengths, :func:`~hybridoc.scales.snap_offset`) is subtracted exactly; but positions of
    1e6 keep only about 1e-10 of their digits, so that each step's displacement is rounded
    there and the loss of a scene far from the origin is noisy at about 1e-9, enough to stall
    L-BFGS's line search. The moved problem computes the same loss and gradient in full
    precision.
    """
    from hybridoc.problems.disc_ocp import translated as moved_scene

    scales = getattr(ocp, "scales", None)
    offset = None if scales is None else scales.offset_array
    if offset is None or not offset.any() or ocp.path is not None:
        return ocp, None  # (path constraints are functions of the state where it is)
    scene = scene_of(ocp)
    n = scene.n_discs
    dx, dy = float(offset[0]), float(offset[1])
    if not (
        np.all(offset[0 : 2 * n : 2] == dx)
        and np.all(offset[1 : 2 * n : 2] == dy)
        and not offset[2 * n :].any()
    ):
        return ocp, None  # not one shift of the whole scene: simulated where it is

    # p + (-d) is p - d exactly: the same numbers as subtracting the offset
    near = moved_scene(scene, np.array([-dx, -dy])).to_ocp()
    return near, offset.copy()


def _disc_step(ocp: HybridOCP, model: ContactModel, integrator: str) -> ca.Function:
    """``(s, u) -> (s_next, eps |u|^2 dt)``: the disc scene's step under ``model``."""
    from hybridoc.solvers.casadi_step import make_step

    scene = scene_of(ocp)
    step = make_step(scene, model, integrator)
    s, u = ca.SX.sym("s", ocp.nx), ca.SX.sym("u", ocp.nu)
    return ca.Function("step", [s, u], [step(s, u), scene.control_weight * scene.dt * ca.sumsqr(u)])


def _with_path_penalty(ocp: HybridOCP, step_fn: ca.Function, path_weight: float) -> ca.Function:
    """The step with the path constraints' penalty at its end state (with its control):
    ``path_weight * dt * |min(c(s_{n+1}, u_n), 0)|^2``."""
    s, u = ca.SX.sym("s", ocp.nx), ca.SX.sym("u", ocp.nu)
    s_next, c_step = step_fn(s, u)
    viol = ca.sumsqr(ca.fmin(ocp.path(s_next, u), 0))
    return ca.Function(
        "step", [s, u], [s_next, c_step + path_weight * ocp.dt * viol], ["s", "u"],
        ["s_next", "cost"],
    )  # fmt: skip


def _rollout_functions(
    step: ca.Function, phi: ca.Function, nx: int, nu: int, N: int
) -> tuple[ca.Function, ca.Function, ca.Function]:
    """Loss, loss with gradient, and rollout of ``N`` steps of ``step`` (``mapaccum``).

    The gradient is the discrete adjoint: a backward ``mapaccum`` of the step's
    vector-Jacobian products (SX), about twice as fast as CasADi's reverse mode of the
    forward ``mapaccum``.
    """
    # an MX step (a switch over modes, hybridoc.solvers.multistart.mode_switch) stays MX
    sym = ca.MX if step.is_a("MXFunction") else ca.SX
    s, u, lam = sym.sym("s", nx), sym.sym("u", nu), sym.sym("lam", nx)
    s_next, c = step(s, u)
    if sym is ca.MX:
        # one reverse sweep of lam^T s_next + c for both inputs: each reverse sweep of an MX
        # graph evaluates its calls' forward passes again (four sweeps: 3 times slower)
        back = ca.jtimes(ca.vertcat(s_next, c), ca.vertcat(s, u), ca.vertcat(lam, 1.0), True)
        adjoint = [back[:nx], back[nx:]]
    else:
        adjoint = [
            ca.jtimes(s_next, s, lam, True) + ca.gradient(c, s),
            ca.jtimes(s_next, u, lam, True) + ca.gradient(c, u),
        ]
    back_step = ca.Function("adjoint_step", [lam, s, u], adjoint)
    sf = ca.SX.sym("sf", nx)
    phi_grad = ca.Function("phi_grad", [sf], [phi(sf), ca.gradient(phi(sf), sf)])
    x0 = ca.MX.sym("x0", nx)
    U = ca.MX.sym("U", nu, N)
    X, C = step.mapaccum("rollout", N)(x0, U)
    phi_N, lam_N = phi_grad(X[:, N - 1])
    J = phi_N + ca.sum2(C)
    X_prev = ca.horzcat(x0, X[:, : N - 1])
    reverse = lambda M: ca.horzcat(*ca.horzsplit(M)[::-1])  # noqa: E731
    lams, grads = back_step.mapaccum("adjoint", N)(lam_N, reverse(X_prev), reverse(U))
    value = ca.Function("loss", [x0, U], [J])
    value_grad = ca.Function("loss_grad", [x0, U], [J, lams[:, N - 1], reverse(grads)])
    rollout = ca.Function("rollout", [x0, U], [ca.horzcat(x0, X)])
    return value, value_grad, rollout


class TerminalLoss:
    """The generic objective with the step length as an input and a terminal
    augmented-Lagrangian term: what gd minimises on problems with terminal constraints or a
    free final time.

    One call of :meth:`evaluate` gives, for controls ``U``, a step ``h = T / N`` and the
    terminal multipliers ``(nu, mu)`` with penalty ``rho``,

    * ``J``: the discrete objective ``phi(s_N) + sum_n c_n`` of :class:`CompiledLoss` (the
      generic time-of-impact step, with the path penalty), at step ``h``;
    * ``A``: the Powell-Hestenes-Rockafellar term of the terminal constraints,
      ``nu . h_eq + rho/2 |h_eq|^2 + 1/(2 rho) sum(max(0, mu - rho h_in)^2 - mu^2)``
      (``h_eq(s_N) = 0``, ``h_in(s_N) >= 0``);
    * ``s_N``, the final state;
    * the gradients of ``J + A`` with respect to ``U`` and to ``T`` (the discrete adjoint
      of the same rollout, carried through ``h``).

    Parameters
    ----------
    problem : ProblemLike
        Any problem (:func:`hybridoc.problem.as_ocp`); a disc scene is simulated by the
        generic step too.
    max_events : int
        Events resolved per step.
    path_weight : float
        Weight of the path-constraint penalty, as in :class:`CompiledLoss`.

    Notes
    -----
    :class:`CompiledLoss` is unchanged (its step length is a constant of the graph); this
    is a separate graph because the step length here is an input.
    """

    def __init__(self, problem: ProblemLike, *, max_events: int = 2, path_weight: float = 1e5):
        from hybridoc.problem import as_ocp
        from hybridoc.solvers.toi_sim import toi_step

        ocp = as_ocp(problem)  # a Scene's to_ocp()
        self.ocp = ocp
        self.steps = N = ocp.steps
        self.nx = nx = ocp.nx
        self.nu = nu = ocp.nu
        self.n_eq = 0 if ocp.terminal_eq is None else int(ocp.terminal_eq.size1_out(0))
        self.n_in = 0 if ocp.terminal_ineq is None else int(ocp.terminal_ineq.size1_out(0))
        h = ca.SX.sym("h")
        step = toi_step(ocp, h, max_events=max_events)
        if ocp.path is not None:
            s, u = ca.SX.sym("s", nx), ca.SX.sym("u", nu)
            s_next, c = step(s, u, h)
            viol = ca.sumsqr(ca.fmin(ocp.path(s_next, u), 0))
            step = ca.Function("toi_step_h", [s, u, h], [s_next, c + path_weight * h * viol])
        self.step = step
        self._fn = Accelerated(self._build(step, N))
        self._x0 = ocp.x0.copy()

    def _build(self, step: ca.Function, N: int) -> ca.Function:
        """``(x0, U, T, nu, mu, rho) -> (J, A, s_N, dJA/dU, dJA/dT)`` (class notes)."""
        ocp, nx, nu = self.ocp, self.nx, self.nu
        s, u, lam, h = ca.SX.sym("s", nx), ca.SX.sym("u", nu), ca.SX.sym("lam", nx), ca.SX.sym("h")
        s_next, c = step(s, u, h)
        back_step = ca.Function(
            "adjoint_step_h",
            [lam, s, u, h],
            [
                ca.jtimes(s_next, s, lam, True) + ca.gradient(c, s),
                ca.jtimes(s_next, u, lam, True) + ca.gradient(c, u),
                ca.jtimes(s_next, h, lam, True) + ca.gradient(c, h),
            ],
        )
        sf = ca.SX.sym("sf", nx)
        nu_m, mu_m, rho = ca.SX.sym("nu", self.n_eq), ca.SX.sym("mu", self.n_in), ca.SX.sym("rho")
        A = ca.SX(0)
        if self.n_eq:
            he = ocp.terminal_eq(sf)
            A += ca.dot(nu_m, he) + 0.5 * rho * ca.sumsqr(he)
        if self.n_in:
            hi = ocp.terminal_ineq(sf)
            A += (ca.sumsqr(ca.fmax(0, mu_m - rho * hi)) - ca.sumsqr(mu_m)) / (2 * rho)
        phi = ocp.phi(sf)
        end = ca.Function("terminal_al", [sf, nu_m, mu_m, rho], [phi, A, ca.gradient(phi + A, sf)])
        x0 = ca.MX.sym("x0", nx)
        U = ca.MX.sym("U", nu, N)
        T = ca.MX.sym("T")
        nu_x, mu_x, rho_x = ca.MX.sym("nu", self.n_eq), ca.MX.sym("mu", self.n_in), ca.MX.sym("rho")
        H = ca.repmat(T / N, 1, N)
        X, C = step.mapaccum("rollout_h", N)(x0, U, H)
        s_N = X[:, N - 1]
        phi_N, A_N, lam_N = end(s_N, nu_x, mu_x, rho_x)
        X_prev = ca.horzcat(x0, X[:, : N - 1])
        reverse = lambda M: ca.horzcat(*ca.horzsplit(M)[::-1])  # noqa: E731
        _, gU, gh = back_step.mapaccum("adjoint_h", N)(lam_N, reverse(X_prev), reverse(U), H)
        return ca.Function(
            "terminal_loss",
            [x0, U, T, nu_x, mu_x, rho_x],
            [phi_N + ca.sum2(C), A_N, s_N, reverse(gU), ca.sum2(gh) / N],
        )

    def evaluate(
        self,
        controls: np.ndarray,
        horizon: float,
        nu: np.ndarray | None = None,
        mu: np.ndarray | None = None,
        rho: float = 1.0,
    ) -> tuple[float, float, np.ndarray, np.ndarray, float]:
        """``(J, A, s_N, d(J + A)/dU (N, nu), d(J + A)/dT)`` of ``(N, nu)`` controls at
        final time ``horizon`` (class notes); ``nu`` and ``mu`` default to zeros."""
        u = np.asarray(controls, dtype=float)
        if u.shape != (self.steps, self.nu):
            raise ControlsError(
                f"controls must have shape ({self.steps}, {self.nu}), got {u.shape}"
            )
        nu = np.zeros(self.n_eq) if nu is None else np.asarray(nu, dtype=float)
        mu = np.zeros(self.n_in) if mu is None else np.asarray(mu, dtype=float)
        J, A, sN, gU, gT = self._fn.call_numpy(self._x0, u.T, float(horizon), nu, mu, float(rho))
        return (
            float(J[0, 0]), float(A[0, 0]), sN.ravel(), gU.T.copy(), float(gT[0, 0])
        )  # fmt: skip

    def constraints(self, s_end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The terminal constraint values ``(h_eq, h_in)`` at a final state."""
        ocp = self.ocp
        he = np.zeros(0) if ocp.terminal_eq is None else np.asarray(ocp.terminal_eq(s_end)).ravel()
        hi = (
            np.zeros(0) if ocp.terminal_ineq is None
            else np.asarray(ocp.terminal_ineq(s_end)).ravel()
        )  # fmt: skip
        return he, hi


_LOSS_FN: Any = None


def _loss_function() -> Any:
    """The torch autograd Function (built on first use: torch is imported lazily)."""
    global _LOSS_FN
    if _LOSS_FN is None:
        import torch

        class _Loss(torch.autograd.Function):
            @staticmethod
            def forward(ctx: Any, u: Any, x0: Any, owner: CompiledLoss) -> Any:
                un = u.detach().cpu().numpy().astype(float)
                xn = x0.detach().cpu().numpy().astype(float)
                if un.shape[0] == 1:
                    J, gu, gx = owner.value_and_grad(un[0], xn[0])
                    vals, gus, gxs = np.array([J]), gu[None], gx[None]
                else:
                    vals, gus, gxs = owner.value_and_grad_batch(un, xn)

                def t(a: Any) -> Any:
                    return torch.as_tensor(np.asarray(a), dtype=u.dtype, device=u.device)

                ctx.save_for_backward(t(gus), t(gxs))
                return t(vals)

            @staticmethod
            def backward(ctx: Any, grad_out: Any) -> tuple[Any, ...]:
                gu, gx = ctx.saved_tensors
                return grad_out[:, None, None] * gu, grad_out[:, None] * gx, None

        _LOSS_FN = _Loss
    return _LOSS_FN
