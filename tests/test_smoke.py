import hybridoc


def test_import_subpackages():
    import hybridoc.problems
    import hybridoc.reference
    import hybridoc.solvers  # noqa: F401

    assert "single-collision" in hybridoc.builtin_names()
