"""The layer-stack data model: what an artist builds in the sidebar, as plain data.

A stack is a base (``Diffuse``, ``Conductor`` or ``Dielectric``) under zero or more
``Coating`` layers, listed bottom to top. Every roughness here is the GGX ``alpha``
(not the artist's squared "roughness"; see :func:`alpha_from_artist_roughness`).

Two ranges matter for each parameter:

- the *valid* range: anything outside it is not a physical material, and constructing
  the layer raises ``ValueError`` naming the field, the value and the range;
- the *trained* range (``TRAINED_RANGES``): what the neural models saw in training.
  Valid values outside it are still rendered exactly by the reference; the neural
  runtime clamps them with :func:`clamp_to_trained` and says what it changed.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
from dataclasses import dataclass, field
from typing import Iterable, Union

import numpy as np

RGB = tuple[float, float, float]

# Every parameter's two ranges, inclusive: field -> (valid range, trained range). The valid range is
# what is physical; the trained range what the neural models saw in training (docs/architecture.md,
# "The layer stack"). The one table of both: everything else reads VALID_RANGES / TRAINED_RANGES.
RANGES: dict[str, tuple[tuple[float, float], tuple[float, float]]] = {
    "roughness": ((0.0, 1.0), (0.01, 1.0)),
    "ior": ((1.0, 4.0), (1.05, 2.0)),
    "eta": ((0.01, 10.0), (0.01, 10.0)),
    "k": ((0.0, 20.0), (0.0, 20.0)),
    "albedo": ((0.0, 1.0), (0.0, 1.0)),
    "thickness": ((0.0, 100.0), (0.0, 5.0)),
    "g": ((-0.99, 0.99), (0.0, 0.0)),
}
VALID_RANGES: dict[str, tuple[float, float]] = {k: v[0] for k, v in RANGES.items()}
TRAINED_RANGES: dict[str, tuple[float, float]] = {k: v[1] for k, v in RANGES.items()}

# Floats per colour channel of a stack's latent code: a latent is (3, LATENT), a latent texture holds
# 3 * LATENT latent channels per texel.
LATENT = 32


class ClampWarning(UserWarning):
    """A parameter was outside the range the networks were trained on and was clamped."""


def _number(layer: str, name: str, value) -> float:
    """``value`` as a float if it is a real number (not a bool, a string or complex)."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ValueError(f"{layer}.{name} must be a number, got {value!r} ({type(value).__name__})")
    return float(value)


def _check_scalar(layer: str, name: str, value, valid_key: str | None = None) -> float:
    lo, hi = VALID_RANGES[valid_key or name]
    v = _number(layer, name, value)
    if not math.isfinite(v) or v < lo or v > hi:
        raise ValueError(f"{layer}.{name} = {value!r} is outside the valid range [{lo}, {hi}]")
    return v


def _check_rgb(layer: str, name: str, value, valid_key: str | None = None) -> RGB:
    if isinstance(value, (str, bytes)):
        raise ValueError(f"{layer}.{name} must be an RGB triple of numbers (or one number), got {value!r}")
    if isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_)):
        value = (value, value, value)
    try:
        items = list(value)
    except TypeError:
        raise ValueError(f"{layer}.{name} must be an RGB triple, got {value!r}") from None
    if len(items) != 3:
        raise ValueError(f"{layer}.{name} must have 3 channels (R, G, B), got {len(items)}: {value!r}")
    return tuple(_check_scalar(layer, f"{name}[{'RGB'[i]}]", x, valid_key or name) for i, x in enumerate(items))  # type: ignore[return-value]


@dataclass(frozen=True)
class Diffuse:
    """Lambertian base with RGB albedo in [0, 1]."""

    albedo: RGB = (0.8, 0.8, 0.8)

    def __post_init__(self):
        object.__setattr__(self, "albedo", _check_rgb("Diffuse", "albedo", self.albedo))


@dataclass(frozen=True)
class Conductor:
    """Rough conductor base: GGX alpha and complex index eta + i k per channel."""

    roughness: float = 0.1
    eta: RGB = (0.2, 0.9, 1.1)
    k: RGB = (3.9, 2.4, 2.2)

    def __post_init__(self):
        object.__setattr__(self, "roughness", _check_scalar("Conductor", "roughness", self.roughness))
        object.__setattr__(self, "eta", _check_rgb("Conductor", "eta", self.eta))
        object.__setattr__(self, "k", _check_rgb("Conductor", "k", self.k))

    @classmethod
    def from_f0(cls, f0: RGB, roughness: float = 0.1) -> "Conductor":
        """A conductor whose normal-incidence reflectance is the artist colour ``f0``.

        Uses eta = 1 (all colour carried by k): F0 = k^2 / (4 + k^2), so
        k = 2 sqrt(F0 / (1 - F0)). This matches F0 exactly and keeps the Fresnel
        curve's grazing rise; the edge tint of measured metals is not modelled.
        """
        f0 = _check_rgb("Conductor", "f0", f0, "albedo")
        k = tuple(float(x) for x in k_from_f0(np.array(f0)))
        return cls(roughness=roughness, eta=(1.0, 1.0, 1.0), k=k)


def k_from_f0(f0: np.ndarray) -> np.ndarray:
    """Extinction k with eta = 1 giving normal-incidence reflectance ``f0`` (any shape, 0..1).

    F0 = k^2 / (4 + k^2)  =>  k = 2 sqrt(F0 / (1 - F0)), capped at the valid k range.
    """
    c = np.clip(np.asarray(f0, dtype=np.float64), 0.0, 0.999)
    return np.minimum(2.0 * np.sqrt(c / (1.0 - c)), VALID_RANGES["k"][1])


@dataclass(frozen=True)
class Dielectric:
    """Rough dielectric base: reflection from a GGX interface over black."""

    roughness: float = 0.1
    ior: float = 1.5

    def __post_init__(self):
        object.__setattr__(self, "roughness", _check_scalar("Dielectric", "roughness", self.roughness))
        object.__setattr__(self, "ior", _check_scalar("Dielectric", "ior", self.ior))


@dataclass(frozen=True)
class Coating:
    """A rough dielectric interface over a homogeneous slab.

    ``albedo`` is the single-scattering albedo (RGB) of the slab's medium,
    ``thickness`` its optical thickness sigma_t * depth (0 = no medium), ``g`` the
    Henyey-Greenstein asymmetry of its phase function.
    """

    roughness: float = 0.05
    ior: float = 1.5
    albedo: RGB = (0.0, 0.0, 0.0)
    thickness: float = 0.0
    g: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "roughness", _check_scalar("Coating", "roughness", self.roughness))
        object.__setattr__(self, "ior", _check_scalar("Coating", "ior", self.ior))
        object.__setattr__(self, "albedo", _check_rgb("Coating", "albedo", self.albedo))
        object.__setattr__(self, "thickness", _check_scalar("Coating", "thickness", self.thickness))
        object.__setattr__(self, "g", _check_scalar("Coating", "g", self.g))


Base = Union[Diffuse, Conductor, Dielectric]
Layer = Union[Diffuse, Conductor, Dielectric, Coating]
BASE_TYPES = (Diffuse, Conductor, Dielectric)


@dataclass(frozen=True)
class Stack:
    """A base under ``coatings`` (bottom to top)."""

    base: Base
    coatings: tuple[Coating, ...] = field(default_factory=tuple)

    def __post_init__(self):
        if not isinstance(self.base, BASE_TYPES):
            raise ValueError(f"Stack.base must be Diffuse, Conductor or Dielectric, got {type(self.base).__name__}")
        coatings = tuple(self.coatings)
        for i, c in enumerate(coatings):
            if not isinstance(c, Coating):
                raise ValueError(f"Stack.coatings[{i}] must be a Coating, got {type(c).__name__}")
        object.__setattr__(self, "coatings", coatings)

    @property
    def layers(self) -> tuple[Layer, ...]:
        """All layers bottom to top: base first."""
        return (self.base, *self.coatings)

    def to_dict(self) -> dict:
        return {"base": layer_to_dict(self.base), "coatings": [layer_to_dict(c) for c in self.coatings]}

    @classmethod
    def from_dict(cls, data: dict) -> "Stack":
        if not isinstance(data, dict) or "base" not in data:
            raise ValueError(f"a stack needs a 'base' entry, got {data!r}")
        if not isinstance(data.get("coatings", []), list):
            raise ValueError(f"a stack's 'coatings' must be a list of layers, got {data['coatings']!r}")
        return cls(
            base=layer_from_dict(data["base"]),
            coatings=tuple(layer_from_dict(c) for c in data.get("coatings", [])),
        )

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "Stack":
        return cls.from_dict(json.loads(text))


LAYER_TYPES = {t.__name__: t for t in (Diffuse, Conductor, Dielectric, Coating)}


def layer_to_dict(layer: Layer) -> dict:
    d = dataclasses.asdict(layer)
    d = {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}
    d["type"] = type(layer).__name__
    return d


def layer_from_dict(data: dict) -> Layer:
    if not isinstance(data, dict):
        raise ValueError(f"a layer must be a mapping with a 'type' entry, got {data!r}")
    data = dict(data)
    kind = data.pop("type", None)
    if kind not in LAYER_TYPES:
        raise ValueError(f"unknown layer type {kind!r}; expected one of {sorted(LAYER_TYPES)}")
    names = {f.name for f in dataclasses.fields(LAYER_TYPES[kind])}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"{kind} has no field(s) {sorted(unknown)}; fields are {sorted(names)}")
    return LAYER_TYPES[kind](**data)


def alpha_from_artist_roughness(r):
    """Artist roughness (perceptual, as in Blender's Principled BSDF) -> GGX alpha = r^2.

    A number gives a float; an array gives an array."""
    a = np.square(np.asarray(r, dtype=np.float64))
    return float(a) if a.ndim == 0 else a


def artist_roughness_from_alpha(alpha: float) -> float:
    return math.sqrt(max(float(alpha), 0.0))


def coating_interface(coating: Coating) -> Dielectric:
    """The single layer a coating's interface is: ``Dielectric(roughness, ior)``, reflection over black.

    The one rule of how the encoders see a coating: a coating (or its interface on top of a stack) is
    encoded as this dielectric, and the layering network adds the slab and what lies below.
    """
    return Dielectric(coating.roughness, coating.ior)


def _clamp(v: float, key: str) -> float:
    lo, hi = TRAINED_RANGES[key]
    return min(max(v, lo), hi)


def _clamp_stack(stack: Stack) -> tuple[Stack, list[str]]:
    notes: list[str] = []

    def fix(layer_name: str, layer: Layer) -> Layer:
        changes = {}
        for f in dataclasses.fields(layer):
            key = f.name if f.name in TRAINED_RANGES else None
            if key is None:
                continue
            v = getattr(layer, f.name)
            if isinstance(v, tuple):
                nv = tuple(_clamp(x, key) for x in v)
            else:
                nv = _clamp(v, key)
            if nv != v:
                lo, hi = TRAINED_RANGES[key]
                notes.append(f"{layer_name}.{f.name} = {v} clamped to {nv} (trained range [{lo}, {hi}])")
                changes[f.name] = nv
        return dataclasses.replace(layer, **changes) if changes else layer

    base = fix(f"base({type(stack.base).__name__})", stack.base)
    coatings = tuple(fix(f"coatings[{i}]", c) for i, c in enumerate(stack.coatings))
    return Stack(base, coatings), notes


def _presets() -> dict[str, Stack]:
    gold = Conductor(roughness=0.08, eta=(0.143, 0.374, 1.442), k=(3.983, 2.385, 1.603))
    copper = Conductor(roughness=0.2, eta=(0.200, 0.924, 1.102), k=(3.912, 2.452, 2.142))
    aluminium = Conductor(roughness=0.3, eta=(1.657, 0.880, 0.521), k=(9.224, 6.270, 4.837))
    return {
        "coated_gold": Stack(gold, (Coating(roughness=0.02, ior=1.5),)),
        "red_car_paint": Stack(
            aluminium,
            (
                Coating(roughness=0.15, ior=1.5, albedo=(0.9, 0.05, 0.05), thickness=1.5),
                Coating(roughness=0.01, ior=1.5),
            ),
        ),
        "lacquered_plastic": Stack(Diffuse((0.05, 0.25, 0.6)), (Coating(roughness=0.03, ior=1.5),)),
        "varnished_wood": Stack(
            Diffuse((0.45, 0.22, 0.08)),
            (Coating(roughness=0.1, ior=1.52, albedo=(0.95, 0.7, 0.3), thickness=0.6),),
        ),
        "frosted_copper": Stack(copper, (Coating(roughness=0.5, ior=1.45),)),
        "three_layer": Stack(
            Diffuse((0.8, 0.8, 0.8)),
            (
                Coating(roughness=0.3, ior=1.4, albedo=(0.2, 0.6, 0.9), thickness=1.0),
                Coating(roughness=0.2, ior=1.6, albedo=(0.9, 0.9, 0.3), thickness=0.5),
                Coating(roughness=0.05, ior=1.5),
            ),
        ),
        "rough_dielectric": Stack(Dielectric(roughness=0.25, ior=1.5)),
        "white_diffuse": Stack(Diffuse((0.8, 0.8, 0.8))),
    }


PRESETS: dict[str, Stack] = _presets()


def preset(name: str) -> Stack:
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; presets are {sorted(PRESETS)}") from None


def iter_params(stack: Stack) -> Iterable[tuple[str, str, object]]:
    """(layer label, field name, value) for every parameter, bottom to top."""
    for i, layer in enumerate(stack.layers):
        label = "base" if i == 0 else f"coatings[{i - 1}]"
        for f in dataclasses.fields(layer):
            yield label, f.name, getattr(layer, f.name)


# ---------------------------------------------------------------------------------------------
# Many stacks at once: a struct of arrays with one row per stack (texels, training data, hits).

BASE_KINDS = ("Diffuse", "Conductor", "Dielectric")


@dataclass
class StackArrays:
    """N stacks with the same number of coatings C, one row each (float64 arrays).

    Base fields not used by a row's base kind hold the defaults of that field and are ignored.
    ``coat_*`` arrays are (N, C) or (N, C, 3); coatings are ordered bottom to top.
    """

    base_kind: np.ndarray  # (N,) int: index into BASE_KINDS
    base_albedo: np.ndarray  # (N, 3)  Diffuse
    base_roughness: np.ndarray  # (N,)  Conductor, Dielectric
    base_eta: np.ndarray  # (N, 3)  Conductor
    base_k: np.ndarray  # (N, 3)  Conductor
    base_ior: np.ndarray  # (N,)  Dielectric
    coat_roughness: np.ndarray  # (N, C)
    coat_ior: np.ndarray  # (N, C)
    coat_albedo: np.ndarray  # (N, C, 3)
    coat_thickness: np.ndarray  # (N, C)
    coat_g: np.ndarray  # (N, C)

    FIELDS = (
        "base_kind",
        "base_albedo",
        "base_roughness",
        "base_eta",
        "base_k",
        "base_ior",
        "coat_roughness",
        "coat_ior",
        "coat_albedo",
        "coat_thickness",
        "coat_g",
    )

    def __len__(self) -> int:
        return int(self.base_kind.shape[0])

    @property
    def n_coatings(self) -> int:
        return int(self.coat_roughness.shape[1])

    @classmethod
    def from_stacks(cls, stacks: "list[Stack]") -> "StackArrays":
        if not stacks:
            raise ValueError("StackArrays.from_stacks needs at least one stack")
        n_coat = {len(s.coatings) for s in stacks}
        if len(n_coat) != 1:
            raise ValueError(f"all stacks in one batch need the same number of coatings, got {sorted(n_coat)}")
        d_base = {
            "albedo": Diffuse().albedo,
            "roughness": Conductor().roughness,
            "eta": Conductor().eta,
            "k": Conductor().k,
            "ior": Dielectric().ior,
        }

        def base_field(s: Stack, name: str):
            return getattr(s.base, name, d_base[name])

        def coat(s: Stack, name: str):
            return [getattr(c, name) for c in s.coatings]

        c = n_coat.pop()
        return cls(
            base_kind=np.array([BASE_KINDS.index(type(s.base).__name__) for s in stacks], dtype=np.int64),
            base_albedo=np.array([base_field(s, "albedo") for s in stacks], dtype=np.float64),
            base_roughness=np.array([base_field(s, "roughness") for s in stacks], dtype=np.float64),
            base_eta=np.array([base_field(s, "eta") for s in stacks], dtype=np.float64),
            base_k=np.array([base_field(s, "k") for s in stacks], dtype=np.float64),
            base_ior=np.array([base_field(s, "ior") for s in stacks], dtype=np.float64),
            coat_roughness=np.array([coat(s, "roughness") for s in stacks], dtype=np.float64).reshape(len(stacks), c),
            coat_ior=np.array([coat(s, "ior") for s in stacks], dtype=np.float64).reshape(len(stacks), c),
            coat_albedo=np.array([coat(s, "albedo") for s in stacks], dtype=np.float64).reshape(len(stacks), c, 3),
            coat_thickness=np.array([coat(s, "thickness") for s in stacks], dtype=np.float64).reshape(len(stacks), c),
            coat_g=np.array([coat(s, "g") for s in stacks], dtype=np.float64).reshape(len(stacks), c),
        )

    @classmethod
    def repeat(cls, stack: Stack, n: int) -> "StackArrays":
        """``n`` copies of one stack (the start of a spatially varying stack)."""
        one = cls.from_stacks([stack])
        return cls(**{f: np.repeat(getattr(one, f), n, axis=0) for f in cls.FIELDS})

    def take(self, index) -> "StackArrays":
        return StackArrays(**{f: getattr(self, f)[index] for f in self.FIELDS})

    def to_matrix(self, dtype=np.float64) -> np.ndarray:
        """(N, P) matrix of every field, for deduplication and hashing (``dtype`` float32: what
        ``rows.distinct_rows`` compares, without the float64 copy)."""
        n = len(self)
        return np.concatenate([getattr(self, f).reshape(n, -1) for f in self.FIELDS], axis=1, dtype=dtype)

    def unique(self) -> "tuple[StackArrays, np.ndarray]":
        """Distinct rows and the inverse index (rows == unique.take(inverse))."""
        _, first, inverse = np.unique(self.to_matrix(), axis=0, return_index=True, return_inverse=True)
        return self.take(first), inverse.reshape(-1)

    def stack(self, i: int) -> Stack:
        """Row ``i`` as a validated Stack."""
        kind = BASE_KINDS[int(self.base_kind[i])]
        if kind == "Diffuse":
            base: Base = Diffuse(tuple(self.base_albedo[i]))
        elif kind == "Conductor":
            base = Conductor(float(self.base_roughness[i]), tuple(self.base_eta[i]), tuple(self.base_k[i]))
        else:
            base = Dielectric(float(self.base_roughness[i]), float(self.base_ior[i]))
        coats = tuple(
            Coating(
                float(self.coat_roughness[i, j]),
                float(self.coat_ior[i, j]),
                tuple(self.coat_albedo[i, j]),
                float(self.coat_thickness[i, j]),
                float(self.coat_g[i, j]),
            )
            for j in range(self.n_coatings)
        )
        return Stack(base, coats)

    def coating_interfaces(self) -> "StackArrays":
        """The interfaces of all coatings as N * C single-layer rows (row i * C + j: coating j of stack i),
        by :func:`coating_interface`'s rule: ``Dielectric(coat_roughness, coat_ior)``."""
        m = len(self) * self.n_coatings
        d = Diffuse().albedo, Conductor().eta, Conductor().k
        return StackArrays(
            base_kind=np.full(m, BASE_KINDS.index("Dielectric"), dtype=np.int64),
            base_albedo=np.tile(np.asarray(d[0], dtype=np.float64), (m, 1)),
            base_roughness=np.asarray(self.coat_roughness, dtype=np.float64).reshape(m),
            base_eta=np.tile(np.asarray(d[1], dtype=np.float64), (m, 1)),
            base_k=np.tile(np.asarray(d[2], dtype=np.float64), (m, 1)),
            base_ior=np.asarray(self.coat_ior, dtype=np.float64).reshape(m),
            **_no_coatings(m),
        )


def _no_coatings(n: int) -> dict:
    return {
        "coat_roughness": np.zeros((n, 0)),
        "coat_ior": np.zeros((n, 0)),
        "coat_albedo": np.zeros((n, 0, 3)),
        "coat_thickness": np.zeros((n, 0)),
        "coat_g": np.zeros((n, 0)),
    }


# StackArrays field -> (its range in RANGES, the base kinds whose rows use it; None: every row).
ARRAY_FIELDS: dict[str, tuple[str, tuple[int, ...] | None]] = {
    "base_albedo": ("albedo", (0,)),
    "base_roughness": ("roughness", (1, 2)),
    "base_eta": ("eta", (1,)),
    "base_k": ("k", (1,)),
    "base_ior": ("ior", (2,)),
    "coat_roughness": ("roughness", None),
    "coat_ior": ("ior", None),
    "coat_albedo": ("albedo", None),
    "coat_thickness": ("thickness", None),
    "coat_g": ("g", None),
}


def _array_shapes(sa: StackArrays) -> dict[str, tuple[int, ...]]:
    n, c = len(sa), sa.n_coatings
    return {
        "base_kind": (n,),
        "base_albedo": (n, 3),
        "base_roughness": (n,),
        "base_eta": (n, 3),
        "base_k": (n, 3),
        "base_ior": (n,),
        "coat_roughness": (n, c),
        "coat_ior": (n, c),
        "coat_albedo": (n, c, 3),
        "coat_thickness": (n, c),
        "coat_g": (n, c),
    }


def _validate_arrays(sa: StackArrays) -> None:
    for name in StackArrays.FIELDS:
        a = getattr(sa, name)
        if np.iscomplexobj(a) or np.asarray(a).dtype.kind not in "biuf":
            raise ValueError(f"StackArrays.{name} must hold real numbers, got dtype {np.asarray(a).dtype}")
    for name, shape in _array_shapes(sa).items():
        a = np.asarray(getattr(sa, name))
        if a.shape != shape:
            raise ValueError(f"StackArrays.{name} must have shape {shape}, got {a.shape}")
    kind = np.asarray(sa.base_kind)
    if np.any((kind < 0) | (kind >= len(BASE_KINDS))):
        raise ValueError(f"StackArrays.base_kind must index {BASE_KINDS}, got values {np.unique(kind).tolist()}")
    for name, (key, _) in ARRAY_FIELDS.items():
        a = np.asarray(getattr(sa, name), dtype=np.float64)
        lo, hi = VALID_RANGES[key]
        bad = ~np.isfinite(a) | (a < lo) | (a > hi)
        if np.any(bad):
            where = tuple(int(i[0]) for i in np.nonzero(bad))
            raise ValueError(f"StackArrays.{name}{list(where)} = {a[where]!r} is outside the valid range [{lo}, {hi}]")


def validate(stacks: "Stack | StackArrays") -> None:
    """Raise ValueError naming the field, the row and the range when ``stacks`` is not a valid Stack or
    StackArrays: malformed, not real, not finite or outside VALID_RANGES (a Stack checks itself when
    it is built, so for one only its type is checked)."""
    if isinstance(stacks, Stack):
        return
    if not isinstance(stacks, StackArrays):
        raise ValueError(f"expected a Stack or StackArrays, got {type(stacks).__name__}")
    _validate_arrays(stacks)


def _clamp_arrays(arrays: StackArrays) -> tuple[StackArrays, list[str]]:
    out = arrays.take(slice(None))
    return out, _field_notes(out, fix=True)


def _field_notes(arrays: StackArrays, fix: bool) -> list[str]:
    """A note per field of ``arrays`` with rows outside its trained range (the rows whose base kind uses it), and
    with ``fix`` the field clamped in place; one field's copy at a time."""
    notes = []
    for name, (key, kinds) in ARRAY_FIELDS.items():
        lo, hi = TRAINED_RANGES[key]
        v = np.asarray(getattr(arrays, name), dtype=np.float64)
        c = np.clip(v, lo, hi)
        changed = (c != v).reshape(len(arrays), int(np.prod(v.shape[1:]))).any(axis=1)
        if kinds is not None:  # only the fields a row's base kind uses matter
            changed &= np.isin(arrays.base_kind, kinds)
        if np.any(changed):
            i, k = int(np.flatnonzero(changed)[0]), int(changed.sum())
            notes.append(
                f"{name}: {k} row{'s' if k != 1 else ''} clamped to the trained range [{lo}, {hi}] "
                f"(first: row {i}, {v[i].tolist()} -> {c[i].tolist()})"
            )
        if fix:
            setattr(arrays, name, c)
    return notes


def clamp_notes(arrays: StackArrays) -> list[str]:
    """``clamp_to_trained(arrays)``'s notes without its clamped copy of every row (147 bytes a row: 2.3 GiB for a
    4096 x 4096 bake of distinct texels): a minimum and a maximum a field where no field leaves its trained range (3
    ms for 262,144 texels, where the copy took 66), else one field's copy at a time."""
    for name, (key, _kinds) in ARRAY_FIELDS.items():
        lo, hi = TRAINED_RANGES[key]
        v = getattr(arrays, name)
        if np.size(v) and (np.min(v) < lo or np.max(v) > hi):
            return _field_notes(arrays, fix=False)
    return []


def clamp_to_trained(stacks: "Stack | StackArrays") -> "tuple[Stack | StackArrays, list[str]]":
    """Every parameter clamped into TRAINED_RANGES: the clamped copy and a note per change (a Stack:
    per layer field; StackArrays: per field, with the count of rows whose base kind uses it)."""
    if isinstance(stacks, Stack):
        return _clamp_stack(stacks)
    if isinstance(stacks, StackArrays):
        return _clamp_arrays(stacks)
    raise ValueError(f"clamp_to_trained needs a Stack or StackArrays, got {type(stacks).__name__}")
