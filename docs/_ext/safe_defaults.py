"""Keep ``autodoc_preserve_defaults`` from reading another function's defaults.

With ``autodoc_preserve_defaults = True`` autodoc shows default values as written in the
source (``iterations=DEFAULT_PBD_ITERATIONS``, not ``iterations=4``). It finds them with
:func:`inspect.getsource`, which reads the file *as it is on disk now* from the line where
the imported code object starts. When the file has changed since the module was imported
(someone edits the code while the pages build; autodoc imports a module once and documents
it a minute later), that line is the start of some other definition, and autodoc either
shows the defaults of the wrong function or fails with
``error while formatting signature for ...: pop from empty list`` (an ``IndexError``: the
definition on disk has fewer defaults than the signature), which ``-W`` turns into a build
error.

This extension wraps autodoc's default-value hook: it first checks that the source found is
the object's own definition (same name, same parameters as the imported signature) and
otherwise leaves the signature with its evaluated defaults; any remaining failure of the hook
does the same. Load it before ``sphinx.ext.autodoc`` (the older Sphinx versions connect the
hook while autodoc is set up).
"""

from __future__ import annotations

import ast
import functools
import importlib
import inspect
import textwrap
from collections.abc import Callable
from typing import Any


def _parameter_names(node: ast.arguments) -> list[str]:
    names = [a.arg for a in (*node.posonlyargs, *node.args)]
    if node.vararg is not None:
        names.append(node.vararg.arg)
    names += [a.arg for a in node.kwonlyargs]
    if node.kwarg is not None:
        names.append(node.kwarg.arg)
    return names


def source_matches(obj: Any, bound_method: bool = False) -> bool:
    """Whether the source :func:`inspect.getsource` finds for ``obj`` is its own definition.

    ``True`` when there is nothing to check (no source, not a function: autodoc's hook then
    does nothing either); ``False`` when the definition found has another name or other
    parameters than the imported object, or does not parse.
    """
    func = getattr(obj, "__func__", obj) if bound_method or inspect.ismethod(obj) else obj
    if not (inspect.isfunction(func) or inspect.ismethod(func)):
        return True
    try:
        source = inspect.getsource(func)
    except (OSError, TypeError):
        return True
    try:
        tree = ast.parse(textwrap.dedent(source))
    except SyntaxError:
        return func.__name__ == "<lambda>"  # a lambda inside a larger expression: autodoc's case
    node = tree.body[0] if tree.body else None
    if func.__name__ == "<lambda>":
        return True
    if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
        return False
    if node.name != func.__name__:
        return False
    try:
        params = list(inspect.signature(func, follow_wrapped=False).parameters)
    except (TypeError, ValueError):
        return True
    return _parameter_names(node.args) == params


def _guarded(hook: Callable[..., Any], obj_index: int) -> Callable[..., Any]:
    if getattr(hook, "_hybridoc_guarded", False):
        return hook

    @functools.wraps(hook)
    def guarded(*args: Any, **kwargs: Any) -> Any:
        obj = args[obj_index] if len(args) > obj_index else kwargs.get("obj")
        bound = args[obj_index + 1] if len(args) > obj_index + 1 else kwargs.get("bound_method")
        if not source_matches(obj, bool(bound)):
            return None
        try:
            return hook(*args, **kwargs)
        except (IndexError, ValueError, SyntaxError):
            return None

    guarded._hybridoc_guarded = True  # type: ignore[attr-defined]
    return guarded


# (module, attribute, index of ``obj`` in the hook's arguments)
_HOOKS = (
    ("sphinx.ext.autodoc._dynamic._signatures", "update_default_value", 0),  # Sphinx >= 9
    ("sphinx.ext.autodoc.preserve_defaults", "update_default_value", 0),  # Sphinx 9, legacy
    ("sphinx.ext.autodoc.preserve_defaults", "update_defvalue", 1),  # Sphinx < 9: (app, obj, b)
)


def install() -> list[str]:
    """Wrap every known form of autodoc's hook; returns the names wrapped."""
    done = []
    for module_name, attr, index in _HOOKS:
        try:
            module = importlib.import_module(module_name)
        except ImportError:
            continue
        hook = getattr(module, attr, None)
        if callable(hook):
            setattr(module, attr, _guarded(hook, index))
            done.append(f"{module_name}.{attr}")
    return done


def setup(app: Any) -> dict[str, Any]:
    install()
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
