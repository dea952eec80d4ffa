"""A sphinx-gallery image scraper for the figures hybridoc returns.

hybridoc's plotting functions (:mod:`hybridoc.plotting`) build ``matplotlib.figure.Figure``
objects without pyplot, so that library code never opens a window or leaks figures. The
standard matplotlib scraper only sees pyplot's figures; this one also renders every such
Figure that a tutorial block bound to a global name (``fig = plot_scene(...)``), once, after
the block that made it.
"""

from __future__ import annotations

from typing import Any

_SEEN = "__gallery_figures_seen__"


def scrape_figures(block: Any, block_vars: dict[str, Any], gallery_conf: dict[str, Any]) -> str:
    """Save the new pyplot-less Figures of a tutorial block and return their reST.

    Parameters
    ----------
    block
        The code block just executed (unused).
    block_vars
        sphinx-gallery's block variables: ``example_globals`` (the tutorial's namespace)
        and ``image_path_iterator`` (where to write images).
    gallery_conf
        sphinx-gallery's configuration (``src_dir`` is used).

    Returns
    -------
    str
        The reST of the images written, empty when the block made no new figure.
    """
    from matplotlib.figure import Figure
    from sphinx_gallery.scrapers import figure_rst

    ns = block_vars["example_globals"]
    seen = ns.setdefault(_SEEN, [])  # the figures themselves: ids could be reused
    new = []
    for value in list(ns.values()):
        if (
            isinstance(value, Figure)
            and getattr(value.canvas, "manager", None) is None  # pyplot's scraper has those
            and not any(value is s for s in seen)
        ):
            seen.append(value)
            new.append(value)
    paths = []
    for fig, path in zip(new, block_vars["image_path_iterator"], strict=False):
        fig.savefig(path, dpi=110, bbox_inches="tight")  # no empty margins
        paths.append(path)
    return figure_rst(paths, gallery_conf["src_dir"]) if paths else ""
