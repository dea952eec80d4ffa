def test_import_subpackages():
    import hybridoc.problems
    import hybridoc.reference
    import hybridoc.solvers

    assert "single-collision" in hybridoc.builtin_names()
    assert hybridoc.reference.solve_reference is not None
    assert hybridoc.solvers.__name__ == "hybridoc.solvers"
    assert hybridoc.problems.load_scene("head-on").name == "head-on"
