"""The albedo calibration's formulas (``addon.core.formula``), which the compiled loops (``addon.core.kernels``)
call while ``calibrate`` calls those loops: a module of its own, so that neither imports the other.

- ``azimuth_cell``: where a relative azimuth falls between the calibration table's azimuth nodes, evenly spaced on
  [0, pi] (``calibrate.AZIMUTHS``): the node below it and the linear weight of the node above.
"""

from __future__ import annotations

import math

from ..formula import arccos, clip, formula, node_below


@formula
def azimuth_cell(cos_phi, nodes):
    """``(q, w)``: the relative azimuth acos(``cos_phi``) lies between azimuth nodes q and q + 1 of ``nodes`` (at
    least 2) evenly spaced on [0, pi], at weight w of node q + 1 (1 - w of node q)."""
    u = arccos(clip(cos_phi, -1.0, 1.0)) * ((nodes - 1) / math.pi)
    q = node_below(u, nodes - 2)
    return q, u - q
