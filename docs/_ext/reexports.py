"""Resolve cross-references to re-exported names (``hybridoc.evaluate``) to where they live.

The API reference documents every object once, in the module that defines it
(``hybridoc.evaluator.evaluate``). Docstrings and pages naturally write the short public name,
``:func:`hybridoc.evaluate```, ``:class:`hybridoc.HybridOCP```, which Sphinx cannot find and
leaves unlinked. On a missing Python reference whose target starts with ``hybridoc.``, this
extension imports the name, takes the defining module and qualified name of the object it
finds (``hybridoc.solve`` is imported lazily by the package's ``__getattr__``; that works too)
and resolves the reference to that. Data without a ``__module__`` (a registry dict re-exported
by its package) is looked up among the documented objects of the same package.
"""

from __future__ import annotations

import importlib
from typing import Any


def _lookup(target: str) -> Any:
    """The object ``target`` names: the longest importable module prefix, then attributes."""
    parts = target.split(".")
    for k in range(len(parts) - 1, 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except Exception:  # noqa: BLE001 - not a module: try a shorter prefix
            continue
        try:
            for attr in parts[k:]:
                obj = getattr(obj, attr)
        except Exception:  # noqa: BLE001
            return None
        return obj
    return None


def canonical_name(target: str, documented: Any = ()) -> str | None:
    """Where the object that ``target`` names is documented, if not at ``target``.

    Functions, classes and methods carry their defining module and qualified name. Data
    (a registry dict) does not: then the documented names (``documented``) that end in the
    same attribute under the same package are searched for the identical object.
    """
    obj = _lookup(target)
    if obj is None:
        return None
    module = getattr(obj, "__module__", None)
    qualname = getattr(obj, "__qualname__", None)
    if isinstance(module, str) and isinstance(qualname, str):
        name = f"{module}.{qualname}"
        return None if name == target else name
    package, _, attr = target.rpartition(".")
    for name in documented:
        if name != target and name.startswith(package + ".") and name.endswith("." + attr):
            if _lookup(name) is obj:
                return name
    return None


def _missing_reference(app: Any, env: Any, node: Any, contnode: Any) -> Any:
    if node.get("refdomain") != "py":
        return None
    target = node.get("reftarget", "")
    if not target.startswith("hybridoc."):
        return None
    domain = env.get_domain("py")
    name = canonical_name(target, domain.objects)
    if name is None:
        return None
    return domain.resolve_xref(
        env, node.get("refdoc", ""), app.builder, node.get("reftype", "obj"), name, node, contnode
    )


def setup(app: Any) -> dict[str, Any]:
    app.connect("missing-reference", _missing_reference)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
