"""The layer-stack model: validation, presets, serialisation, trained-range clamping."""

import math

import pytest

from addon.core import stack as st


def test_presets_are_valid_and_cover_the_material_families():
    assert len(st.PRESETS) >= 6
    kinds = {type(s.base) for s in st.PRESETS.values()}
    assert kinds == {st.Diffuse, st.Conductor, st.Dielectric}
    assert max(len(s.coatings) for s in st.PRESETS.values()) >= 3


@pytest.mark.parametrize("name", sorted(st.PRESETS))
def test_stack_json_round_trip(name):
    s = st.preset(name)
    assert st.Stack.from_json(s.to_json()) == s


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: st.Coating(roughness=-0.1), "Coating.roughness"),
        (lambda: st.Coating(ior=0.9), "Coating.ior"),
        (lambda: st.Coating(thickness=float("nan")), "Coating.thickness"),
        (lambda: st.Coating(albedo=(0.1, 1.5, 0.2)), "Coating.albedo[G]"),
        (lambda: st.Diffuse(albedo=(0.1, 0.2)), "Diffuse.albedo"),
        (lambda: st.Conductor(k=(1, 2, -3)), "Conductor.k[B]"),
        (lambda: st.Dielectric(ior="glass"), "Dielectric.ior"),
        (lambda: st.Coating(g=1.0), "Coating.g"),
    ],
)
def test_bad_values_name_field_value_and_range(make, field):
    with pytest.raises(ValueError) as err:
        make()
    assert field in str(err.value)


def test_stack_rejects_wrong_layer_types():
    with pytest.raises(ValueError, match="base"):
        st.Stack(st.Coating())
    with pytest.raises(ValueError, match=r"coatings\[0\]"):
        st.Stack(st.Diffuse(), (st.Diffuse(),))


def test_unknown_preset_and_layer_type_are_clear():
    with pytest.raises(ValueError, match="unknown preset"):
        st.preset("velvet")
    with pytest.raises(ValueError, match="unknown layer type"):
        st.layer_from_dict({"type": "Velvet"})
    with pytest.raises(ValueError, match="no field"):
        st.layer_from_dict({"type": "Diffuse", "colour": [1, 1, 1]})


def test_from_f0_reproduces_normal_incidence_reflectance():
    f0 = (0.95, 0.64, 0.54)
    c = st.Conductor.from_f0(f0, roughness=0.2)
    for target, eta, k in zip(f0, c.eta, c.k):
        r = ((eta - 1) ** 2 + k**2) / ((eta + 1) ** 2 + k**2)
        assert math.isclose(r, target, rel_tol=1e-9)


def test_clamp_to_trained_reports_every_change():
    s = st.Stack(st.Diffuse(), (st.Coating(roughness=0.0, ior=2.5, thickness=10.0),))
    clamped, notes = st.clamp_to_trained(s)
    c = clamped.coatings[0]
    assert (c.roughness, c.ior, c.thickness) == (0.01, 2.0, 5.0)
    assert len(notes) == 3 and all("clamped" in n for n in notes)
    same, none = st.clamp_to_trained(st.preset("lacquered_plastic"))
    assert none == [] and same == st.preset("lacquered_plastic")


def test_artist_roughness_mapping_round_trips():
    for r in (0.0, 0.1, 0.5, 1.0):
        assert math.isclose(st.artist_roughness_from_alpha(st.alpha_from_artist_roughness(r)), r)
