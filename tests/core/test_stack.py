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
    for target, eta, k in zip(f0, c.eta, c.k, strict=True):
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


@pytest.mark.parametrize(
    "build,field",
    [
        (lambda: st.Diffuse("111"), "Diffuse.albedo"),
        (lambda: st.Diffuse(b"111"), "Diffuse.albedo"),
        (lambda: st.Diffuse(("0.5", 0.5, 0.5)), "Diffuse.albedo[R]"),
        (lambda: st.Conductor(roughness="0.5"), "Conductor.roughness"),
        (lambda: st.Conductor(roughness=True), "Conductor.roughness"),
        (lambda: st.Dielectric(ior=1.5 + 0j), "Dielectric.ior"),
        (lambda: st.Coating(thickness=None), "Coating.thickness"),
        (lambda: st.Coating(albedo=(True, 0.0, 0.0)), "Coating.albedo[R]"),
    ],
)
def test_strings_bools_and_complex_numbers_are_not_parameters(build, field):
    with pytest.raises(ValueError, match=field.replace("[", r"\[").replace("]", r"\]")):
        build()


def test_numpy_numbers_are_parameters():
    import numpy as np

    c = st.Coating(
        roughness=np.float32(0.25),
        ior=np.float64(1.5),
        albedo=np.array([0.1, 0.2, 0.3]),
        thickness=np.array(2.0),
        g=np.int64(0),
    )
    assert c.roughness == 0.25 and c.albedo == (0.1, 0.2, 0.3) and c.thickness == 2.0
    assert st.Diffuse(np.float32(0.5)).albedo == (0.5, 0.5, 0.5)


def test_one_table_holds_both_ranges_of_every_field():
    assert set(st.RANGES) == set(st.VALID_RANGES) == set(st.TRAINED_RANGES)
    for key, (valid, trained) in st.RANGES.items():
        assert valid[0] <= trained[0] <= trained[1] <= valid[1], key
    assert {k for k, _ in st.ARRAY_FIELDS.values()} <= set(st.RANGES)


def test_validate_names_field_row_and_range_of_stack_arrays():
    import numpy as np

    a = st.StackArrays.from_stacks([st.preset("red_car_paint")] * 3)
    st.validate(a)
    st.validate(st.preset("red_car_paint"))
    bad = a.take(slice(None))
    bad.coat_thickness = bad.coat_thickness.copy()
    bad.coat_thickness[2, 1] = 101.0
    with pytest.raises(ValueError, match=r"coat_thickness\[2, 1\].*\[0.0, 100.0\]"):
        st.validate(bad)
    bad = a.take(slice(None))
    bad.base_k = bad.base_k + 1j
    with pytest.raises(ValueError, match="base_k must hold real numbers"):
        st.validate(bad)
    bad = a.take(slice(None))
    bad.coat_ior = bad.coat_ior[:, :1]
    with pytest.raises(ValueError, match=r"coat_ior must have shape \(3, 2\)"):
        st.validate(bad)
    with pytest.raises(ValueError, match="Stack or StackArrays"):
        st.validate({"base": "Diffuse"})
    assert np.all(np.isfinite(a.to_matrix()))


def test_clamp_to_trained_of_arrays_matches_the_stack_rule_and_counts_rows():
    import numpy as np

    s = st.Stack(st.Conductor(roughness=0.001), (st.Coating(ior=3.0, thickness=20.0, g=0.5),))
    one, notes = st.clamp_to_trained(s)
    arrays, arr_notes = st.clamp_to_trained(st.StackArrays.repeat(s, 4))
    assert arrays.stack(3) == one and len(notes) == len(arr_notes) == 4
    assert any(n.startswith("coat_thickness: 4 rows") for n in arr_notes)
    # a field the row's base kind does not use is not reported
    d = st.StackArrays.repeat(st.Stack(st.Diffuse(0.5)), 2)
    d.base_roughness = np.zeros(2)
    assert st.clamp_to_trained(d)[1] == []
    with pytest.raises(ValueError, match="Stack or StackArrays"):
        st.clamp_to_trained([s])


def test_a_coating_encodes_as_its_interface_in_both_forms():
    s = st.preset("three_layer")
    rows = st.StackArrays.from_stacks([s, s]).coating_interfaces()
    assert len(rows) == 2 * len(s.coatings) and rows.n_coatings == 0
    for j, c in enumerate(s.coatings):
        assert rows.stack(len(s.coatings) + j) == st.Stack(st.coating_interface(c))


@pytest.mark.parametrize(
    "text",
    [
        '{"base": {"type": "Diffuse"}, "coatings": null}',
        '{"base": {"type": "Diffuse"}, "coatings": "Coating"}',
        '{"base": [1, 2]}',
        '{"base": {"type": "Diffuse"}, "coatings": [3]}',
    ],
)
def test_a_malformed_stack_text_raises_value_error(text):
    """The documented error for a bad stack is ValueError: these raised TypeError ('NoneType' object is not
    iterable, ...), which a caller catching ValueError did not see."""
    with pytest.raises(ValueError):
        st.Stack.from_json(text)


def test_clamp_notes_are_clamp_to_trained_s_without_its_copy():
    """What a bake says of its distinct texels: the same notes as ``clamp_to_trained``, none for rows inside the
    trained ranges (checked by a minimum and a maximum a field, where the clamped copy took 66 ms of a bake)."""
    inside = st.StackArrays.from_stacks([st.preset("varnished_wood"), st.preset("red_car_paint")][:1] * 3)
    assert st.clamp_notes(inside) == [] == st.clamp_to_trained(inside)[1]
    smooth = st.Stack(st.Diffuse((0.5, 0.5, 0.5)), (st.Coating(0.0, 2.5),))
    mixed = st.StackArrays.from_stacks([st.preset("varnished_wood"), smooth, smooth])
    notes = st.clamp_notes(mixed)
    assert notes == st.clamp_to_trained(mixed)[1] and len(notes) == 2  # roughness and ior, 2 rows each
