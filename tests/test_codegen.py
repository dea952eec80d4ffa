"""The compiled C path of the simulation: bit for bit the virtual machine's numbers."""

from __future__ import annotations

import hashlib
import json
import os
import stat
import subprocess
import time
import warnings
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import hybridoc
from hybridoc import compiled
from hybridoc.solvers import codegen


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


# ---------------------------------------------------------------- a code cache you can trust


@pytest.fixture
def private(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """An empty private cache folder, with the one-time warnings forgotten."""
    cache = tmp_path / "cache"
    cache.mkdir(mode=0o700)
    monkeypatch.setenv("HYBRIDOC_CACHE", str(cache))
    monkeypatch.delenv("HYBRIDOC_CACHE_MAX_MB", raising=False)
    monkeypatch.setattr(compiled, "_WARNED", set())
    return cache


def _probe() -> ca.Function:
    x = ca.SX.sym("x")
    return ca.Function("trust_probe", [x], [ca.cos(x) * x])


def _planted(at: Path, marker: Path) -> None:
    """A library whose constructor writes ``marker`` when it is loaded, at ``at``."""
    src = marker.with_suffix(".c")
    src.write_text(
        "#include <stdio.h>\n"
        "__attribute__((constructor)) static void planted(void) {\n"
        f'  FILE *f = fopen("{marker}", "w");\n'
        '  if (f) { fputs("ran", f); fclose(f); }\n'
        "}\n"
    )
    subprocess.run(
        [codegen.compiler(), "-shared", "-fPIC", str(src), "-o", str(at)],
        check=True,
        capture_output=True,
    )


def _fake_library(folder: Path, name: str, size: int, age_s: float, record: bool = True) -> Path:
    """Random bytes at a library's name, with hybridoc's record of them, last used ``age_s``
    seconds ago."""
    lib = folder / f"{name}_{hashlib.sha256(name.encode()).hexdigest()[:24]}.so"
    data = os.urandom(size)
    lib.write_bytes(data)
    if record:
        rec = lib.with_name(lib.name + ".sha256")
        rec.write_text(f"{hashlib.sha256(data).hexdigest()}  {lib.name}\n")
    t = time.time() - age_s
    os.utime(lib, (t, t))
    return lib


@pytest.fixture
def marker(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("plant") / "constructor_ran"


def test_a_planted_library_is_not_loaded(compiling: None, private: Path, marker: Path) -> None:
    from hybridoc.solvers.compiled import CompiledLoss

    u = hybridoc.as_ocp("head-on").u_guess * 1.3
    vm = CompiledLoss("head-on", integrator="exact")
    expected = vm.value_and_grad(u)
    planted = [vm._value._lib, vm._value_grad._lib]
    for lib in planted:  # at the exact names the cache loads, with no record
        _planted(lib, marker)
    loss = CompiledLoss("head-on", integrator="exact")
    assert not marker.exists(), "a planted library was loaded"
    assert not loss._value.compiled and not loss._value_grad.compiled
    assert not any(lib.exists() for lib in planted)  # deleted, to be compiled again
    got = loss.value_and_grad(u)  # the loss still works, on the virtual machine
    assert got[0] == expected[0]
    np.testing.assert_array_equal(got[1], expected[1])


def test_a_tampered_library_is_not_loaded(compiling: None, private: Path, marker: Path) -> None:
    fn = _probe()
    built = codegen.Accelerated(fn, wait=True)
    assert built.compiled, built.error
    record = built._lib.with_name(built._lib.name + ".sha256")
    assert record.is_file() and stat.S_IMODE(built._lib.stat().st_mode) == 0o600
    _planted(built._lib, marker)  # other bytes under the recorded name
    acc = codegen.Accelerated(fn)
    assert not acc.compiled and not marker.exists()
    assert float(acc(0.5)) == float(fn(0.5))
    # one flipped byte of a genuine library is refused as well
    rebuilt = codegen.Accelerated(fn, wait=True)
    assert rebuilt.compiled, rebuilt.error
    data = bytearray(rebuilt._lib.read_bytes())
    data[len(data) // 2] ^= 0xFF
    rebuilt._lib.write_bytes(bytes(data))
    assert not codegen.Accelerated(fn).compiled
    assert not marker.exists()


def test_a_cache_folder_others_can_write_is_refused_and_left_as_it_is(
    compiling: None, private: Path, marker: Path
) -> None:
    # an older hybridoc under umask 002 made the folder 0775, or the user pointed
    # HYBRIDOC_CACHE at a shared one: anyone else could have put a library and its record
    # there. Nothing is loaded from it, and it is not re-permissioned (a shared folder must
    # stay open to its other users): compiled code is off, with one warning saying why.
    fn = _probe()
    assert codegen.Accelerated(fn, wait=True).compiled  # a genuine, recorded library
    (old,) = private.glob("*.so")
    _planted(old, marker)  # what someone else could have done...
    old.with_name(old.name + ".sha256").write_text(  # ...with a record to match
        f"{hashlib.sha256(old.read_bytes()).hexdigest()}  {old.name}\n"
    )
    planted = old.read_bytes()
    private.chmod(0o777)
    assert "other users can write" in codegen.check_cache_dir()
    with pytest.warns(codegen.CacheWarning, match=r"not private: other users can write to it"):
        acc = codegen.Accelerated(fn, hot=0)
    assert stat.S_IMODE(private.stat().st_mode) == 0o777  # never chmod-ed
    assert not acc.compiled and acc._calls_left == -1  # nothing loaded, nothing built
    assert not marker.exists() and old.read_bytes() == planted  # not run, not touched
    assert float(acc(0.5)) == float(fn(0.5))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the warning is given once
        assert not codegen.Accelerated(fn, wait=True).compiled
    assert len(list(private.glob("*.so"))) == 1  # left as it was


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="needs chown (root)")
def test_a_cache_folder_of_another_user_is_refused(compiling: None, private: Path) -> None:
    fn = _probe()
    assert codegen.Accelerated(fn, wait=True).compiled
    os.chown(private, 65534, 65534)
    assert "owned by uid 65534" in codegen.check_cache_dir()
    with pytest.warns(codegen.CacheWarning, match="not private"):
        assert not codegen.Accelerated(fn).compiled


def test_a_new_cache_folder_is_private(
    compiling: None, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    cache = tmp_path / "new" / "cache"
    monkeypatch.setenv("HYBRIDOC_CACHE", str(cache))
    acc = codegen.Accelerated(_probe(), wait=True)
    assert acc.compiled, acc.error
    assert stat.S_IMODE(cache.stat().st_mode) == 0o700


def test_an_existing_readable_cache_folder_is_used_as_it_is(
    compiling: None, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    # an older hybridoc created the folder 0755: nobody else can write to it, so it is safe
    # to load from; its mode is the user's choice and is left as it is
    cache = tmp_path / "old"
    cache.mkdir(mode=0o755)
    cache.chmod(0o755)
    monkeypatch.setenv("HYBRIDOC_CACHE", str(cache))
    acc = codegen.Accelerated(_probe(), wait=True)
    assert acc.compiled, acc.error
    assert stat.S_IMODE(cache.stat().st_mode) == 0o755


def test_eviction_keeps_the_cache_under_its_bound(private: Path) -> None:
    libs = [_fake_library(private, f"f{k}", 1000, age_s=100.0 - k) for k in range(5)]
    stranger = private / "notes.bin"
    stranger.write_bytes(b"x" * 10_000)
    stale, fresh = (libs[0].with_name(f"{libs[0].name}.{pid}.tmp") for pid in (11, 12))
    for tmp, age in ((stale, 7200.0), (fresh, 0.0)):  # a dead build's temporary, a live one's
        tmp.write_bytes(b"")
        os.utime(tmp, (time.time() - age,) * 2)
    removed = codegen.evict(limit=2500)
    # the least recently used, and the dead build's temporary
    assert sorted(removed) == sorted([*(lib.name for lib in libs[:3]), stale.name])
    fresh.unlink()
    left = [p for p in private.iterdir() if p != stranger]
    assert sorted(p.name for p in left if p.suffix == ".so") == sorted(lib.name for lib in libs[3:])
    assert sum(p.stat().st_size for p in left) <= 2500
    assert stranger.read_bytes() == b"x" * 10_000  # not hybridoc's: not counted, not deleted


def test_the_bound_is_set_by_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(compiled, "_WARNED", set())
    monkeypatch.delenv("HYBRIDOC_CACHE_MAX_MB", raising=False)
    assert codegen.cache_limit() == 500_000_000
    monkeypatch.setenv("HYBRIDOC_CACHE_MAX_MB", "2.5")
    assert codegen.cache_limit() == 2_500_000
    monkeypatch.setenv("HYBRIDOC_CACHE_MAX_MB", "lots")
    with pytest.warns(codegen.CacheWarning, match="HYBRIDOC_CACHE_MAX_MB"):
        assert codegen.cache_limit() == 500_000_000


def test_a_zero_bound_keeps_no_library_on_disk(
    compiling: None, private: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("HYBRIDOC_CACHE_MAX_MB", "0")
    fn = _probe()
    acc = codegen.Accelerated(fn, wait=True)
    assert acc.compiled, acc.error  # loaded before it was evicted
    assert float(acc(0.5)) == float(fn(0.5))
    assert list(private.iterdir()) == []


def test_cache_info_and_clear(private: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from hybridoc.cli import main

    _fake_library(private, "kept", 3000, age_s=0.0)
    _fake_library(private, "old", 2000, age_s=10.0, record=False)  # an older hybridoc's
    (private / "notes.txt").write_text("mine")
    (private / "sub").mkdir()
    assert main(["cache", "info", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["path"] == str(private) and info["safe"] and info["mode"] == "0700"
    assert (info["libraries"], info["unverified"], info["other_files"]) == (2, 1, 2)
    assert 5000 < info["size_bytes"] < 5200 and info["limit_bytes"] == 500_000_000
    assert main(["cache", "info"]) == 0
    out = capsys.readouterr().out
    assert str(private) in out and "0700, private" in out and "2 (1 without a matching" in out

    assert main(["cache", "clear"]) == 0
    assert "removed 3 files" in capsys.readouterr().out
    assert sorted(p.name for p in private.iterdir()) == ["notes.txt", "sub"]
    assert (private / "notes.txt").read_text() == "mine"
    assert main(["cache", "info", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["libraries"] == 0

    private.chmod(0o770)
    assert main(["cache", "info"]) == 1
    err = capsys.readouterr().err
    assert "hybridoc: warning: the code cache" in err and "not private" in err


def test_cache_info_and_clear_without_directory_descriptors(
    private: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Windows has no O_DIRECTORY (and compiles nothing): info and clear answer, not crash
    _fake_library(private, "f", 100, age_s=1.0)
    monkeypatch.delattr(os, "O_DIRECTORY")
    info = codegen.cache_info()
    assert info["exists"] and info["libraries"] == 0
    assert codegen.clear_cache()["removed"] == 0
    assert len(list(private.glob("*.so"))) == 1


# ---------------------------------------------------------------- the native (ctypes) call


def _wait_compiled(acc: codegen.Accelerated) -> None:
    deadline = time.time() + 120
    while not acc.compiled and acc.error is None:
        assert time.time() < deadline, "compilation did not finish"
        time.sleep(0.05)
    assert acc.compiled, acc.error


def test_native_loss_gradient_equal_casadi_call_and_central_differences(compiling: None) -> None:
    from hybridoc.problems import load_problem
    from hybridoc.solvers.compiled import CompiledLoss

    # 24 steps: the collision happens inside the horizon, and the C code compiles in ~1 s
    scene = load_problem("single-collision").with_steps(24)
    loss = CompiledLoss(scene, "direct", "exact")
    vg = loss._value_grad
    u = scene.initial_controls() * 1.1
    x0 = loss._x0
    vm = [np.asarray(v) for v in vg.vm(x0, u.T)]
    for _ in range(codegen.HOT_CALLS):
        loss.value_and_grad(u)
    _wait_compiled(vg)
    assert vg.native is not None
    J, gU, gx = loss.value_and_grad(u)
    # the same numbers, bit for bit, as CasADi's call of the library and its virtual machine
    lib = [np.asarray(v) for v in vg.fn(x0, u.T)]
    for ref in (vm, lib):
        assert J == ref[0].item()
        np.testing.assert_array_equal(gx, ref[1].ravel())
        np.testing.assert_array_equal(gU, ref[2].T)
    assert loss.value(u) == J
    # against central differences, along random directions of the controls and of x0
    rng = np.random.default_rng(0)
    h = 1e-6
    for _ in range(3):
        du = rng.standard_normal(u.shape)
        fd = (loss.value(u + h * du) - loss.value(u - h * du)) / (2 * h)
        assert abs(fd - float(np.sum(gU * du))) <= 1e-6 * max(1.0, abs(fd))
        dx = rng.standard_normal(x0.shape)
        fd = (loss.value(u, x0 + h * dx) - loss.value(u, x0 - h * dx)) / (2 * h)
        assert abs(fd - float(gx @ dx)) <= 1e-6 * max(1.0, abs(fd))
    # a batch through the mapped function: each start as alone
    U = np.stack([u, 0.9 * u, u + 0.05])
    Jb, gUb, gxb = loss.value_and_grad_batch(U)
    for b in range(3):
        Jo, gUo, gxo = loss.value_and_grad(U[b])
        assert abs(Jb[b] - Jo) <= 1e-12 * abs(Jo)
        np.testing.assert_allclose(gUb[b], gUo, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(gxb[b], gxo, rtol=1e-12, atol=1e-14)


def test_native_function_shapes_sparse_outputs_and_threads(compiling: None) -> None:
    import threading

    x, A, s = ca.SX.sym("x", 3), ca.SX.sym("A", 2, 3), ca.SX.sym("s")
    y = ca.vertcat(ca.SX(1, 1), s * x[1], ca.SX(1, 1))  # structural zeros: scattered back
    fn = ca.Function("native_probe", [x, A, s], [ca.mtimes(A, x) * s, y, ca.sumsqr(A)])
    assert not fn.sparsity_out(1).is_dense()
    acc = codegen.Accelerated(fn, wait=True)
    assert acc.compiled and acc.native is not None, acc.error

    def expected(xv: np.ndarray, Av: np.ndarray, sv: float) -> list[np.ndarray]:
        return [np.asarray(o) for o in fn(xv, Av, sv)]

    rng = np.random.default_rng(1)
    xv, Av = rng.standard_normal(3), rng.standard_normal((2, 3))
    got = acc.call_numpy(xv, Av, 0.7)
    for g, e in zip(got, expected(xv, Av, 0.7), strict=True):
        assert g.shape == e.shape
        np.testing.assert_array_equal(g, e)
    with pytest.raises(ValueError, match="values"):
        acc.call_numpy(xv[:2], Av, 0.7)
    # concurrent callers: each gets its own work arrays, no mixed-up results
    inputs = [(rng.standard_normal(3), rng.standard_normal((2, 3)), float(k)) for k in range(8)]
    results: dict[int, list[np.ndarray]] = {}

    def worker(k: int) -> None:
        for _ in range(200):
            results[k] = acc.call_numpy(*inputs[k])

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for k, args in enumerate(inputs):
        for g, e in zip(results[k], expected(*args), strict=True):
            np.testing.assert_array_equal(g, e)


def test_call_numpy_without_a_compiler_is_casadi_call(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HYBRIDOC_CODEGEN", "0")
    x = ca.SX.sym("x", 2)
    fn = ca.Function("vm_probe", [x], [ca.sin(x), ca.sumsqr(x)])
    acc = codegen.Accelerated(fn)
    assert acc.native is None and not acc.compiled
    out = acc.call_numpy(np.array([0.3, -1.2]))
    np.testing.assert_array_equal(out[0], np.sin([[0.3], [-1.2]]))
    assert out[1].shape == (1, 1) and out[1][0, 0] == 0.3**2 + 1.2**2
