"""The reference's closed-form phases follow the problem's capability, not its type (issue
#30): a problem that offers a :class:`~hybridoc.capabilities.LinearControlFlow` gets them
whatever its class, and a disc scene without one takes the generic DOP853 flow, which is
exact for the same polynomial phases."""

from __future__ import annotations

import numpy as np

import hybridoc
from hybridoc.capabilities import Capabilities
from hybridoc.ocp import HybridOCP
from hybridoc.problems import load_problem
from hybridoc.reference.shooting import (
    has_closed_form_phases,
    is_disc_scene,
    newton,
    shooting_system,
)


def _scene() -> HybridOCP:
    return hybridoc.as_ocp(load_problem("single-collision"))


def test_a_linear_control_flow_gets_the_closed_form_phases_whatever_the_type() -> None:
    ocp = _scene()
    plain = HybridOCP(
        f=ocp.f, L=ocp.L, phi=ocp.phi, guards=list(ocp.guards), x0=ocp.x0,
        horizon=ocp.horizon, steps=ocp.steps, capabilities=ocp.capabilities,
    )  # fmt: skip
    assert type(plain) is HybridOCP
    assert has_closed_form_phases(plain) and is_disc_scene(plain)
    seq = [ocp.guards[0].name]
    S, P = shooting_system(ocp, seq), shooting_system(plain, seq)
    assert S.disc and P.disc
    np.testing.assert_array_equal(P.A, ocp.capabilities.flow.A)
    assert P.eps == ocp.capabilities.flow.eps
    z = np.random.default_rng(0).normal(size=S.nz)
    z[ocp.nx] = 0.5 * ocp.horizon  # the event time
    for a, b in zip(S.residual(z), P.residual(z), strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_disc_scene_without_the_capability_takes_the_generic_flow() -> None:
    ocp = _scene()
    bare = ocp.replace(capabilities=Capabilities())
    assert not has_closed_form_phases(bare)
    seq = [ocp.guards[0].name]
    S, G = shooting_system(ocp, seq), shooting_system(bare, seq)
    assert S.disc and not G.disc
    z0, ok, _ = S.solve_nlp(np.array([0.5 * ocp.horizon]), np.zeros((2, 2 * ocp.nu)))
    nr = newton(S, z0)
    assert ok and nr.converged
    # the generic flow's DOP853 phases are exact for these polynomials: the same root
    ng = newton(G, nr.z)
    assert ng.converged
    np.testing.assert_allclose(ng.z, nr.z, rtol=1e-9, atol=1e-12)
