def test_import_subpackages():
    import hybridoc.problems
    import hybridoc.reference
    import hybridoc.solvers

    assert "single-collision" in hybridoc.builtin_names()
    assert hybridoc.reference.solve_reference is not None
    assert hybridoc.solvers.__name__ == "hybridoc.solvers"
    assert hybridoc.problems.load_scene("head-on").name == "head-on"


def test_import_from_the_repository_root():
    """``import hybridoc`` and ``python -m pytest`` work from a source checkout's root, where
    the bare ``hybridoc/`` folder shadows the installed package (hybridoc/__init__.py extends
    its ``__path__``)."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    code = (
        "import hybridoc, hybridoc.problems, hybridoc.methods; "
        "print(hybridoc.__file__); print(hybridoc.solve('head-on', 'dt').cost)"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert Path(lines[0]).parent == root / "hybridoc"  # the source folder, not the install
    assert abs(float(lines[1]) - 0.082682740993) < 1e-9


def test_version_is_the_package_metadata() -> None:
    import tomllib
    from pathlib import Path

    import hybridoc

    meta = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert hybridoc.__version__ == meta["project"]["version"]
