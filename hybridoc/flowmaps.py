"""Flow maps integrated by CVODES, for problems whose flow has no closed form.

A :class:`~hybridoc.ocp.HybridOCP` built without a ``flow_map`` gets
:func:`integrator_flow_map`; the judge's kernels sample the same integration at several
fractions of a step (:func:`integrator_flow_samples`).
"""

from __future__ import annotations

from collections.abc import Sequence

import casadi as ca

__all__ = ["integrator_flow_map", "integrator_flow_samples"]


def integrator_flow_map(f: ca.Function, L: ca.Function) -> ca.Function:
    """Flow map ``(s, u, h) -> (s(h), cost)`` from CVODES at tight tolerances."""
    return integrator_flow_samples(f, L, [1.0], name="flow_map")


def integrator_flow_samples(
    f: ca.Function, L: ca.Function, fractions: Sequence[float], *, name: str = "flow_samples"
) -> ca.Function:
    """``(s, u, h) -> (s(h * fractions), cost(h * fractions))`` by one CVODES call.

    ``fractions`` are increasing in (0, 1]; the outputs have one column per fraction.
    """
    nx, nu = f.size1_in(0), f.size1_in(1)
    s = ca.MX.sym("s", nx)
    u = ca.MX.sym("u", nu)
    h = ca.MX.sym("h")
    xs = ca.SX.sym("x", nx)
    ps = ca.SX.sym("p", nu + 1)
    us, hs = ps[:nu], ps[nu]
    # time scaled to [0, 1] so that h is a parameter (and h = 0 is allowed)
    dae = {"x": xs, "p": ps, "ode": hs * f(xs, us), "quad": hs * L(xs, us)}
    # quad_err_con: without it CVODES steps by the state alone, and a state that is easy to
    # integrate (a polynomial) gives long steps and a running cost off by 1e-4 relative
    opts = {
        "abstol": 1e-13,
        "reltol": 1e-13,
        "max_num_steps": 100000,
        "show_eval_warnings": False,
        "quad_err_con": True,
    }
    grid = [float(x) for x in fractions]
    integ = ca.integrator(f"{name}_int", "cvodes", dae, 0.0, grid, opts)
    res = integ(x0=s, p=ca.vertcat(u, h))
    return ca.Function(name, [s, u, h], [res["xf"], res["qf"]], ["s", "u", "h"], ["s_end", "cost"])
