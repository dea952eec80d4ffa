"""Contact models as objects (issue 20): one object with its options and TOI setting through
the torch simulator and the compiled step; a new model with an option in one class plus one
registration line; repr, equality and hashing (models are cache keys)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

import hybridoc
from hybridoc.errors import SceneError
from hybridoc.solvers.casadi_step import make_step
from hybridoc.solvers.compiled import CompiledLoss
from hybridoc.solvers.contacts import CONTACT_MODELS, contact_model, register, unregister
from hybridoc.solvers.contacts.compliant import Compliant
from hybridoc.solvers.contacts.direct import Direct
from hybridoc.solvers.contacts.lcp import LCP
from hybridoc.solvers.simulator import Simulator


@pytest.fixture(scope="module")
def head_on():
    scene = hybridoc.load_scene("head-on")
    return scene, scene.initial_controls()


def test_simulator_takes_a_model_with_options(head_on):
    scene, u = head_on
    obj = Simulator(scene, contact=Compliant(stiffness=2e4)).loss(u)
    by_name = Simulator(scene, contact="compliant", stiffness=2e4).loss(u)
    parsed = Simulator(scene, contact=contact_model("compliant", stiffness=2e4)).loss(u)
    assert float(obj) == float(by_name) == float(parsed)
    stiff = Simulator(scene, contact=Compliant(stiffness=5e4)).loss(u)
    assert float(obj) != float(stiff)  # the option counts


def test_compiled_loss_takes_a_model_with_its_toi(head_on):
    scene, u = head_on
    values = {
        CompiledLoss(scene, LCP(toi="velocity")).value(u),
        CompiledLoss(scene, "lcp/velocity").value(u),
        CompiledLoss(scene, "lcp", toi="velocity").value(u),
        CompiledLoss(scene, LCP(toi="both"), toi="velocity").value(u),  # toi= folded in
    }
    assert len(values) == 1
    comp = CompiledLoss(scene, contact=LCP(toi="both"))
    assert comp.model == LCP() and comp.settings["toi"] == "both"
    torch_loss = float(Simulator(scene, contact=LCP(toi="both")).loss(u))
    assert comp.value(u) == pytest.approx(torch_loss, rel=1e-10)
    assert comp.value(u) == CompiledLoss(scene, "lcp/both").value(u)


def test_make_step_takes_the_model(head_on):
    scene, _ = head_on
    s = np.concatenate([scene.initial_state()[: 2 * scene.n_discs], [3.0, 0.0, -3.0, 0.0]])
    u = np.full(scene.n_controls, 5.0)
    a = np.asarray(make_step(scene, Direct(toi="none"))(s, u))
    b = np.asarray(make_step(scene, "direct", toi="none")(s, u))
    c = np.asarray(make_step(scene, "direct/none")(s, u))
    assert np.array_equal(a, b) and np.array_equal(a, c)


def test_contact_model_parses_once():
    lcp = LCP(toi="both")
    assert contact_model(lcp) is lcp
    assert contact_model(lcp, toi="both") is lcp
    assert contact_model(lcp, toi=None) is lcp
    other = contact_model(lcp, toi="none")
    assert other == LCP(toi="none") and lcp.toi == "both"  # a copy; the instance unchanged
    soft = Compliant(stiffness=2e4)
    assert contact_model(soft, toi="both") is soft  # no time of impact: ignored
    with pytest.raises(SceneError, match="options cannot be given"):
        contact_model(soft, stiffness=1e3)
    with pytest.raises(SceneError, match="conflicts"):
        contact_model("lcp/none", toi="both")
    assert contact_model("lcp", toi=None) == LCP()


def test_replace_repr_eq_hash():
    assert repr(LCP(toi="both")) == "LCP(toi='both')"
    assert repr(Compliant(stiffness=2e4)).startswith("Compliant(stiffness=20000.0, damping=")
    assert LCP().replace(toi="none") == LCP(toi="none")
    assert Compliant(stiffness=2e4).replace(damping=1.0).options == {
        "stiffness": 2e4,
        "damping": 1.0,
    }
    with pytest.raises(SceneError, match="no option"):
        LCP().replace(stiffness=1.0)
    assert LCP() == contact_model("lcp/both") and hash(LCP()) == hash(contact_model("lcp"))
    assert LCP(toi="none") != LCP(toi="both")
    assert Direct() != LCP()  # same options, another model
    assert Compliant(stiffness=2e4) == Compliant() != Compliant(stiffness=5e4)  # by value
    cache = {LCP(): 1, Compliant(stiffness=2e4): 2}
    assert cache[contact_model("lcp")] == 1 and cache[Compliant(stiffness=20000)] == 2
    assert LCP().settings() == {"contact": "lcp", "toi": "both"}


def test_a_new_model_with_an_option_is_one_class_and_one_registration_line(head_on):
    scene, u = head_on

    @register  # the one registration line
    class ScaledDirect(Direct):
        """``direct`` impulses scaled by ``scale`` (a test model; torch only)."""

        name = "scaled-direct"
        summary = "direct impulses times a factor"
        compiled = False

        def __init__(self, scale: float = 1.0, **options: Any) -> None:
            super().__init__(**options)
            self.scale = float(scale)

        def contact_impulses(self, sim: Any, nrm: Any, w: Any, active: Any) -> Any:
            return self.scale * super().contact_impulses(sim, nrm, w, active)

    try:
        assert CONTACT_MODELS["scaled-direct"] is ScaledDirect
        model = contact_model("scaled-direct/none", scale=0.5)
        assert model == ScaledDirect(scale=0.5, toi="none")
        assert model.options == {"scale": 0.5, "toi": "none"}
        assert repr(model) == "ScaledDirect(scale=0.5, toi='none')"
        assert model.replace(toi="both").label == "scaled-direct/both"
        one = float(Simulator(scene, contact=ScaledDirect(scale=1.0)).loss(u))
        assert one == float(Simulator(scene, contact="direct").loss(u))
        half = Simulator(scene, contact="scaled-direct", scale=0.5).loss(torch.tensor(u))
        assert float(half) != one
        with pytest.raises(SceneError, match="no CasADi form"):
            make_step(scene, model)
    finally:
        unregister("scaled-direct")
    assert "scaled-direct" not in CONTACT_MODELS
