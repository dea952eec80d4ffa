"""The compiled C path of the simulation: bit for bit the virtual machine's numbers."""

from __future__ import annotations

import time

import numpy as np
import pytest

import hybridoc
from hybridoc.solvers import codegen


@pytest.fixture
def compiling(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    if codegen.compiler() is None:
        pytest.skip("no C compiler on this machine")
    monkeypatch.setenv("HYBRIDOC_CODEGEN", "1")
    monkeypatch.setenv("HYBRIDOC_CACHE", str(tmp_path))


def test_compiled_loss_and_gradient_equal_the_virtual_machine(compiling: None) -> None:
    from hybridoc.solvers.compiled import CompiledLoss

    loss = CompiledLoss("head-on", integrator="exact")
    u = hybridoc.as_ocp("head-on").u_guess * 1.3
    before = loss.value_and_grad(u)
    for _ in range(codegen.HOT_CALLS):  # a hot function is compiled
        loss.value_and_grad(u)
    deadline = time.time() + 120
    while not loss._value_grad.compiled and loss._value_grad.error is None:
        assert time.time() < deadline, "compilation did not finish"
        time.sleep(0.1)
    assert loss._value_grad.compiled, loss._value_grad.error
    after = loss.value_and_grad(u)
    assert before[0] == after[0]
    np.testing.assert_array_equal(before[1], after[1])
    np.testing.assert_array_equal(before[2], after[2])
    # a second object finds the library in the cache and loads it at once
    again = CompiledLoss("head-on", integrator="exact")
    assert again._value_grad.compiled


def test_no_compiler_keeps_the_virtual_machine(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HYBRIDOC_CODEGEN", "0")
    from hybridoc.solvers.compiled import CompiledLoss

    loss = CompiledLoss("head-on")
    assert not loss._value_grad.compiled
    assert np.isfinite(loss.value(hybridoc.as_ocp("head-on").u_guess))


def test_compilation_waits_for_hot_calls(compiling: None) -> None:
    import casadi as ca

    x = ca.SX.sym("x")
    fn = ca.Function("hot_probe", [x], [ca.sin(x) * x])
    acc = codegen.Accelerated(fn, hot=3)
    for _ in range(2):
        assert float(acc(0.5)) == float(fn(0.5))
    assert acc._calls_left == 1 and not acc._lib.exists()  # a cold function: no compiler run
    acc(0.5)
    assert acc._calls_left == -1
    deadline = time.time() + 120
    while not acc.compiled and acc.error is None:
        assert time.time() < deadline, "compilation did not finish"
        time.sleep(0.05)
    assert acc.compiled, acc.error
    assert float(acc(0.5)) == float(fn(0.5))
