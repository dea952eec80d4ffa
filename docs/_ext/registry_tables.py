"""Sphinx directives that render hybridoc's registries as tables, read when the pages build.

``.. hybridoc-contact-models::``
    Every contact model of :data:`hybridoc.solvers.contacts.CONTACT_MODELS`: name, class,
    whether it is an impulse model (and so takes a time-of-impact correction of
    :data:`~hybridoc.solvers.contacts.TOI_MODES`), whether it has a CasADi step (the compiled
    path of gradient descent), and its one-line summary.
``.. hybridoc-methods::``
    Every solver of :data:`hybridoc.methods.METHODS`: ``method=`` name, the function
    that runs it, its summary and the options it accepts (read from the function's signature).
``.. hybridoc-problems::``
    Every built-in problem: the disc scenes (:func:`hybridoc.problems.builtin_names`) and the
    library (:func:`hybridoc.problems.library_names`), with state and control sizes, grid,
    horizon and one line of description.

A registered model, method or problem added later appears without editing the pages. The
tables are generated as reStructuredText (``list-table``) and parsed in place, so the roles
in them (``:class:``, ``:func:``) link into the API reference.
"""

from __future__ import annotations

from typing import Any

from docutils import nodes
from docutils.parsers.rst import Directive
from docutils.statemachine import StringList


def _list_table(headers: list[str], rows: list[list[str]], widths: str | None = None) -> list[str]:
    lines = [".. list-table::", "   :header-rows: 1"]
    if widths:
        lines.append(f"   :widths: {widths}")
    lines.append("")
    for row in [headers, *rows]:
        for k, cell in enumerate(row):
            lines.append(("   * - " if k == 0 else "     - ") + (cell or ""))
    return lines


def _yes(flag: bool) -> str:
    return "yes" if flag else "no"


class _Table(Directive):
    has_content = False

    def lines(self) -> list[str]:  # pragma: no cover - interface
        raise NotImplementedError

    def run(self) -> list[Any]:
        container = nodes.container()
        source = self.state_machine.input_lines.source(
            self.lineno - self.state_machine.input_offset - 1
        )
        text = StringList(self.lines(), source=source)
        self.state.nested_parse(text, self.content_offset, container)
        return container.children


class ContactModels(_Table):
    def lines(self) -> list[str]:
        from hybridoc.solvers.contacts import CONTACT_MODELS, TOI_MODES

        toi = ", ".join(f"``{m}``" for m in TOI_MODES)
        rows = []
        for name, cls in CONTACT_MODELS.items():
            rows.append(
                [
                    f"``{name}``",
                    f":class:`~{cls.__module__}.{cls.__qualname__}`",
                    f"yes: {toi}" if cls.impulse_based else "no",
                    _yes(cls.compiled),
                    cls.summary,
                ]
            )
        headers = ["name", "class", "impulse model (TOI modes)", "CasADi step", "summary"]
        return _list_table(headers, rows, "10 16 22 10 42")


class Methods(_Table):
    def lines(self) -> list[str]:
        from hybridoc.methods import METHODS

        rows = []
        for name, m in METHODS.items():
            fn = m.function()
            opts = ", ".join(f"``{o}``" for o in m.option_names())
            rows.append(
                [
                    f"``{name}``",
                    f":func:`~{fn.__module__}.{fn.__qualname__}`",
                    m.summary,
                    f":class:`~{m.options.__module__}.{m.options.__qualname__}`: {opts}",
                    f"{m.tolerance:.0e}",
                ]
            )
        headers = ["method", "function", "summary", "options", "crossval tolerance"]
        return _list_table(headers, rows, "10 18 30 32 10")


class Problems(_Table):
    def lines(self) -> list[str]:
        from hybridoc.problems import builtin_names, library_names, load_problem, load_scene
        from hybridoc.problems.library import describe

        rows = []
        for name in builtin_names():
            scene = load_scene(name)
            ocp = scene.to_ocp()
            rows.append(
                [
                    f"``{name}``",
                    "disc scene",
                    str(ocp.nx),
                    str(ocp.nu),
                    str(ocp.steps),
                    f"{ocp.horizon:.6g}",
                    scene.description,
                ]
            )
        for name in library_names():
            ocp = load_problem(name)
            rows.append(
                [
                    f"``{name}``",
                    "library",
                    str(ocp.nx),
                    str(ocp.nu),
                    str(ocp.steps),
                    f"{ocp.horizon:.6g}",
                    describe(name),
                ]
            )
        headers = ["name", "kind", "nx", "nu", "N", "T", "description"]
        return _list_table(headers, rows, "18 10 5 5 6 8 48")


def setup(app: Any) -> dict[str, Any]:
    app.add_directive("hybridoc-contact-models", ContactModels)
    app.add_directive("hybridoc-methods", Methods)
    app.add_directive("hybridoc-problems", Problems)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
