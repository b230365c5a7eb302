"""Each paper's complete material as a named model (the combinations the papers ship).

Models registered in their family files and already complete materials:

==========================  ===================================================================
``gotanda2010``             Blinn-Phong + Lambert·(1 − F0) (Gotanda 2012 eq 1) — blinn_phong.py
``gotanda2012-layered``     Gotanda 2012 dual layer (eq 2-9) — layered.py
``nielsen-phong``, ``nielsen-blinn-phong``, ``nielsen-mixture``  Nielsen eq 1-3 + Lambert — nielsen.py
``schuler``                 Schüler 2.5 (Lambert + optimized specular, 4 variants) — schuler.py
``cook-torrance``           Lambert + Beckmann, V-cavity, exact Fresnel — microfacet.py
==========================  ===================================================================

Assembled here from lobes of several families:

``ggx-lambert``
    Lambert + GGX / Smith height-correlated / Schlick microfacet specular, uncoupled. The common
    real-time material and shadecap's default scene model; both ``albedo`` and ``f0`` enter
    linearly, so the per-texel solver eliminates them in closed form.
``gotanda2012``
    Gotanda 2012's Blinn-Phong-Oren-Nayar: the physically based Blinn-Phong of eq 1 with the
    improved Oren-Nayar diffuse of eq 25 in place of Lambert, one shininess for both (eq 21: the
    paper's point that both lobes describe the same V-cavity microsurface), and the diffuse
    weighted by (1 − F0) as in eq 1.
``gotanda2014``
    Gotanda 2014: GGX D, Smith height-correlated G, Schlick F specular (eq 1, with the G of its
    footnote 3) + the fitted microfacet diffuse of eq 8 (which carries its own (1 − f0)).
"""

from __future__ import annotations

from collections.abc import Mapping

from torch import Tensor

from .blinn_phong import gotanda_blinn_phong, gotanda_blinn_phong_cosine
from .environment import Environment
from .geometry import Angles
from .lambert import Lambert
from .microfacet import Microfacet
from .microfacet_diffuse import MicrofacetDiffuse
from .model import Model, SumModel, register
from .oren_nayar import gotanda_on_improved
from .params import ALBEDO, F0, ROUGHNESS
from .roughness import roughness_to_shininess


@register("ggx-lambert", "Lambert + GGX/Smith height-correlated/Schlick specular; the default scene model")
def ggx_lambert() -> Model:
    diffuse = Lambert()
    diffuse.name = "lambert"
    spec = Microfacet(D="ggx", G="smith-correlated", F="schlick")
    spec.name = "microfacet"
    return SumModel(diffuse, spec, description="Lambert + GGX microfacet specular")


@register("gotanda2012", "Gotanda 2012: physically based Blinn-Phong + improved Oren-Nayar (eq 25)·(1 − F0)")
class Gotanda2012(Model):
    """Gotanda 2012 Blinn-Phong + improved Oren-Nayar (eq 1 with eq 25 for the diffuse).

    f_r = (1 − F0) f_ON,eq25(ρ, s) + (0.0397436 s + 0.0856832) F_schlick(F0, l·h) (n·h)^s / max(n·l, n·v)
    with s = roughness_to_shininess(r) shared by both lobes (eq 21). Parameters: albedo, f0, roughness.
    """

    params = (ALBEDO, F0, ROUGHNESS)

    def brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        s = roughness_to_shininess(p["roughness"])
        diffuse = gotanda_on_improved(g, p["albedo"] * (1.0 - p["f0"]), s, form="eq25")
        return diffuse + gotanda_blinn_phong(g, p["f0"], s)

    def cosine_brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        s = roughness_to_shininess(p["roughness"])
        diffuse = gotanda_on_improved(g, p["albedo"] * (1.0 - p["f0"]), s, form="eq25", cosine=True)
        return diffuse + gotanda_blinn_phong_cosine(g, p["f0"], s)

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """The closed forms of its two lobes — the improved Oren-Nayar at ρ (1 − F0)
        (:class:`~materials.oren_nayar.GotandaONImproved`) and the Blinn-Phong lobe
        (:class:`~materials.blinn_phong.GotandaBlinnPhong`) — summed, F0 acting on both: ``−ρ`` times the diffuse
        lobe's albedo derivative on the first. Each albedo and f0 channel acts on its own colour channel."""
        from .blinn_phong import GotandaBlinnPhong
        from .oren_nayar import GotandaONImproved

        if not self.shades_as(Gotanda2012):
            return None
        albedo, f0, r = p["albedo"], p["f0"], p["roughness"]
        diffuse, dd = GotandaONImproved(form="eq25").cosine_brdf_jacobian(g, {"albedo": albedo * (1.0 - f0),
                                                                              "roughness": r})
        spec, ds = GotandaBlinnPhong().cosine_brdf_jacobian(g, {"f0": f0, "roughness": r})
        return diffuse + spec, {"albedo": (1.0 - f0) * dd["albedo"], "f0": ds["f0"] - albedo * dd["albedo"],
                                "roughness": dd["roughness"] + ds["roughness"]}

    def environment(self, env: Environment, n: Tensor, v: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        """Diffuse part only, through the improved Oren-Nayar SH scaling (2012 eq 27-29)."""
        from .oren_nayar import GotandaONImproved

        on = GotandaONImproved(form="eq25")
        return on.environment(env, n, v, {"albedo": p["albedo"] * (1.0 - p["f0"]), "roughness": p["roughness"]})


@register("gotanda2014", "Gotanda 2014: GGX/Smith correlated/Schlick specular + fitted microfacet diffuse (eq 8)")
def gotanda2014(diffuse: str = "fitted") -> Model:
    """Options: ``diffuse="fitted"`` (eq 8, real-time) or ``"numerical"`` (eq 4, slow reference)."""
    d = MicrofacetDiffuse(method=diffuse)
    d.name = "microfacet-diffuse"
    spec = Microfacet(D="ggx", G="smith-correlated", F="schlick")
    spec.name = "microfacet"
    return SumModel(d, spec, description="GGX specular + Gotanda 2014 microfacet diffuse")
