"""How a bound material answers the integrator's one query per bounce (``shade``), built from
smaller methods; the interface itself is declared in :mod:`addon.core.render.materials`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import kernels
from ..bsdf.base import BSDFSample


@dataclass
class Shading:
    """A bound material's answer for one bounce: ``f_light`` (V, 3) f at the next-event
    directions, ``pdf_light`` (V,) the BSDF's solid-angle pdf there (None when not asked for or
    V = 0), ``sample`` the BSDF sample of every hit."""

    f_light: np.ndarray
    pdf_light: np.ndarray | None
    sample: BSDFSample


def finish_sample(wi, pdf, f) -> BSDFSample:
    """A BSDFSample from proposed directions, their pdf and the evaluated f (``kernels.finish_proposals``)."""
    wi, weight, pdf, valid = kernels.finish_proposals(*(kernels.float64_rows(a) for a in (wi, pdf, f)))
    false = np.zeros(len(wi), dtype=bool)
    return BSDFSample(wi, weight, pdf, false, false.copy(), valid)


class ShadeByParts:
    """``shade`` from ``eval``, ``pdf`` and ``sample``: a BSDF that samples and evaluates apart."""

    def shade(self, wo, light_wi, light_rows, u_lobe, u, need_pdf) -> Shading:
        f, pdf = np.zeros((0, 3)), None
        if len(light_rows):
            f = self.eval(light_wi, wo[light_rows], light_rows)
            pdf = self.pdf(light_wi, wo[light_rows], light_rows) if need_pdf else None
        return Shading(f, pdf, self.sample(wo, u_lobe, u))


class ShadeByProposal:
    """``shade`` for a material that proposes directions (``sample_direction``, exact pdf) and
    evaluates the proposals in the same ``eval`` call as the next-event directions."""

    def shade(self, wo, light_wi, light_rows, u_lobe, u, need_pdf) -> Shading:
        prop_wi, prop_pdf = self.sample_direction(wo, u_lobe, u)
        v = len(light_rows)
        f_all = self.eval(
            np.concatenate([light_wi, prop_wi]),
            np.concatenate([wo[light_rows], wo]),
            np.concatenate([light_rows, np.arange(len(wo))]),
        )
        pdf = self.pdf(light_wi, wo[light_rows], light_rows) if need_pdf and v else None
        return Shading(f_all[:v], pdf, finish_sample(prop_wi, prop_pdf, f_all[v:]))
