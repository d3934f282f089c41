"""The model set of one decoder size: its four ONNX networks, their cards, one loader and one cache.

    models = load_models("tiny")                   # cached per (size, threads)
    f = models.eval_brdf(z, wi, wo, top)           # (N, 3) f in 1/sr, without the cosine
    sigma_w = models.proxy_params(z)               # (N, 2) proxy parameters of the sampling network

Every decoder size has its own latent space, so a size ships as a set of files in ``addon/models``:

- ``decoder_<size>.onnx`` (inputs ``z`` (B, 32), ``wi``, ``wo`` (B, 3); output ``f`` (B,)) and its fused
  RGB graph ``decoder_<size>_rgb.onnx`` (same weights; ``zc`` (1 or B, 3W) -> ``f`` (B, 3), where ``zc`` is the
  latents through the first layer: ``decoder_<size>_latents.onnx``, ``z`` (B, 3, 32) -> ``zc``,
  :meth:`ModelSet.project_latents`);
- ``encoder_<size>.onnx`` (input ``x`` (B, N_FEATURES); output ``z`` (B, 32));
- ``layering_<size>.onnx`` (``z_top``, ``z_bottom`` (B, 32), ``albedo``, ``thickness`` (B,) -> ``z``);
- ``sampling_<size>.onnx`` (``z`` (B, 3, 32) -> ``sigma``, ``w`` (B,)).

Each network has a model card ``<name>.json`` beside it. :func:`read_card` is the one reader: the card
must be JSON, name its network (``name``), give the sha256 of its own files (``files``) and, for every
network but the decoder, of the files it was trained with (``trained_with``); widths must be positive.
A file that is a Git LFS pointer, does not match its card, or was trained against other files than
those beside it raises :class:`ModelFileError` naming the file and what is wrong; a missing file
raises ``FileNotFoundError``. The decoder and encoder load with the set; the layering and sampling
networks when first used (a single-layer stack needs neither).

A decoder whose card says ``"remainder": true`` holds the *remainder* of a layered stack's BRDF, the
light that entered the top coat; ``eval_brdf`` adds the exact reflection at the top interface
(``top_lobe``) given the stack's top coating (``top``: alpha, ior). Other decoders hold the whole BRDF
and ``top`` changes nothing.

``resolve_size`` turns the model-size setting ("auto" or a size) into a size, for every consumer.
"""

from __future__ import annotations

import hashlib
import json
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from .. import kernels
from ..bsdf.frame import dot
from ..rows import distinct_rows
from ..stack import LATENT
from . import calibrate, proxy, top_lobe
from .features import N_FEATURES
from .session import ChunkedSession

MODEL_DIR = Path(__file__).resolve().parents[2] / "models"
SIZES = ("tiny", "small", "medium", "paper")
AUTO = "auto"
# The size the renderer, the previews and the bakes use when the setting is "auto": the fastest
# (docs/decoders_bench.md, 2-core development machine: tiny 5.7 M, small 2.5 M RGB evaluations per
# second); larger sizes are chosen explicitly or per material by the render quality setting
# (``addon.core.quality``).
DEFAULT_SIZE = "tiny"
ROLES = ("decoder", "encoder", "layering", "sampling")
# What each network was trained with (its card's ``trained_with`` must name these files of its size).
TRAINED_WITH = {
    "decoder": (),
    "encoder": ("decoder",),
    "layering": ("encoder", "decoder"),
    "sampling": ("encoder", "decoder", "layering"),
}
# Floats of one hidden layer's activations per ONNX Runtime call (1.5 MB): the decoder's chunk is
# that over 3 x its width, 4,096 RGB queries for the tiny decoder, 512 for the paper's: half
# that ran 3-10% slower for tiny, small and medium since the graph normalises its directions
# (more element-wise work per call to amortise), twice that slower again. The other networks'
# chunks are half of it over their width (1,536 rows for the 128-wide encoder and layering
# network: 10% more layering throughput than 4,096 rows, benchmarks/bench_bake.py).
DECODER_CHUNK_FLOATS = 393_216
LFS_POINTER = b"version https://git-lfs"


class ModelFileError(OSError):
    """A shipped model file or its card is damaged, or does not belong with the files beside it."""


def file_digest(path: Path | str) -> str:
    """sha256 of a model file, as the cards record it: read once for each version of the file (its inode, size and
    modification time), since every export of a scene checks the models (the viewport's at every edit: 44 files,
    27 MB, 60% of a small scene's edit)."""
    p = Path(path)
    st = p.stat()
    key = (str(p.absolute()), st.st_ino, st.st_size, st.st_mtime_ns)
    with _DIGESTS_LOCK:
        got = _DIGESTS.get(key)
    if got is None:
        got = hashlib.sha256(p.read_bytes()).hexdigest()
        with _DIGESTS_LOCK:
            _DIGESTS[key] = got
    return got


_DIGESTS: dict = {}  # file_digest's: (path, inode, size, modification time) -> sha256
_DIGESTS_LOCK = threading.Lock()


def file_name(role: str, size: str) -> str:
    """``<role>_<size>.onnx``."""
    return f"{role}_{size}.onnx"


def _positive_ints(card: dict, card_path: Path) -> None:
    arch = card.get("architecture", {})
    if not isinstance(arch, dict):
        raise ModelFileError(f"model card {card_path.name}: 'architecture' must be an object, got {arch!r}")
    for key in ("width", "depth", "latent", "n_features"):
        if key in arch:
            v = arch[key]
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ModelFileError(
                    f"model card {card_path.name}: architecture.{key} must be a positive integer, got {v!r}"
                )
    if arch.get("latent", LATENT) != LATENT:
        raise ModelFileError(f"model card {card_path.name}: latent size {arch['latent']} but the runtime's is {LATENT}")


def _digest_map(card: dict, key: str, card_path: Path) -> dict[str, str]:
    m = card.get(key)
    if not isinstance(m, dict) or not m or not all(isinstance(v, str) and len(v) == 64 for v in m.values()):
        raise ModelFileError(
            f"model card {card_path.name} has no valid {key!r} (file name -> sha256); "
            f"re-export the model (python -m onnx_export.export ...)"
        )
    return m


def _check_file(path: Path, digest: str, card_path: Path) -> None:
    if not path.is_file():
        raise FileNotFoundError(
            f"neural model file {path} is missing; export it with `python -m onnx_export.export` "
            f"(available here: {sorted(p.name for p in path.parent.glob('*.onnx'))})"
        )
    with open(path, "rb") as f:
        head = f.read(len(LFS_POINTER))
    if head.startswith(LFS_POINTER):
        raise ModelFileError(f"{path.name} is a Git LFS pointer, not the model: fetch the models with `git lfs pull`")
    got = file_digest(path)
    if got != digest:
        raise ModelFileError(
            f"{path.name} does not match its card {card_path.name} (sha256 {got[:12]}..., the card "
            f"says {digest[:12]}...): the file was replaced, renamed from another size or damaged"
        )


def read_card(role: str, size: str, model_dir: Path | str | None = None) -> dict:
    """The checked model card of network ``role`` of ``size``: JSON, naming this network, positive
    widths, and every file it names (its own, and those it was trained with) present with that digest."""
    if role not in ROLES:
        raise ValueError(f"unknown network role {role!r}; roles are {list(ROLES)}")
    d = Path(model_dir) if model_dir is not None else MODEL_DIR
    onnx_path = d / file_name(role, size)
    card_path = onnx_path.with_suffix(".json")
    if not card_path.is_file():
        if not onnx_path.is_file():
            _check_file(onnx_path, "", card_path)  # raises FileNotFoundError naming the model
        raise FileNotFoundError(f"model card {card_path} is missing: every model ships with its card")
    try:
        card = json.loads(card_path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ModelFileError(
            f"model card {card_path.name} is not valid JSON ({e}); restore it from the "
            f"repository or re-export the model"
        ) from None
    if not isinstance(card, dict):
        raise ModelFileError(f"model card {card_path.name} must hold a JSON object, got {type(card).__name__}")
    if card.get("name") != onnx_path.stem:
        raise ModelFileError(
            f"model card {card_path.name} is the card of {card.get('name')!r}, not of "
            f"{onnx_path.stem!r}: it was renamed from another model"
        )
    _positive_ints(card, card_path)
    own = _digest_map(card, "files", card_path)
    if onnx_path.name not in own:
        raise ModelFileError(f"model card {card_path.name} does not name {onnx_path.name} in 'files' ({sorted(own)})")
    for name, digest in own.items():
        _check_file(d / name, digest, card_path)
    needed = [file_name(r, size) for r in TRAINED_WITH[role]]
    if needed:
        trained = _digest_map(card, "trained_with", card_path)
        for name in needed:
            if name not in trained:
                raise ModelFileError(f"model card {card_path.name} does not say which {name} it was trained with")
            if not (d / name).is_file() or file_digest(d / name) != trained[name]:
                raise ModelFileError(
                    f"{onnx_path.name} was trained with another {name} than the one in {d.name}/: its latents do not "
                    f"match it; retrain {onnx_path.name} or restore the {name} it was trained with"
                )
    return card


def _session(path: Path, threads: int, chunk: int = 4096) -> ChunkedSession:
    """A ChunkedSession of a checked file; a file ONNX Runtime cannot load raises ModelFileError."""
    try:
        return ChunkedSession(path, threads, chunk)
    except (FileNotFoundError, ValueError):
        raise
    except Exception as e:  # onnxruntime's InvalidProtobuf, Fail, ...: not a loadable model
        raise ModelFileError(f"{path.name} is not a loadable ONNX model ({type(e).__name__}: {e})") from None


def _directions(w, name: str) -> np.ndarray:
    if np.iscomplexobj(w):
        raise ValueError(f"{name} must be real directions, got complex values")
    a = np.asarray(w, dtype=np.float64)
    if a.ndim == 1 and a.shape[0] == 3:
        a = a[None]
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3) (or (3,)), got {a.shape}")
    if not np.all(np.isfinite(a)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(a), axis=1))[0])
        raise ValueError(f"{name} must be finite; row {bad} is {a[bad].tolist()}")
    return a


def _unit_or_up(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 unit directions of rows ``w`` (normalised in float64) and whether each is usable:
    nonzero and above the horizon; unusable rows become +z (their output is zeroed)."""
    w = np.asarray(w, dtype=np.float64)
    n2 = dot(w, w)
    ok = (n2 > 0.0) & (w[:, 2] > 0.0) & np.isfinite(n2)
    u = w * (1.0 / np.sqrt(np.where(ok, n2, 1.0)))[:, None]
    if not ok.all():
        u[~ok] = (0.0, 0.0, 1.0)
    return u.astype(np.float32), ok


# Squared lengths float32 holds with room for the graph's own normalisation (|w|^2 in float32,
# clamped at 1e-30): rows outside are scaled to unit length here first, in float64.
_FLOAT32_SQUARED_LENGTH = (1e-28, 1e36)


def _float32_rows(w: np.ndarray) -> np.ndarray:
    """Finite float64 directions ``w`` as float32 rows for the RGB decoder graph, which normalises
    them itself: only lengths that would underflow or overflow in float32 are scaled first."""
    lo, hi = _FLOAT32_SQUARED_LENGTH
    n2 = dot(w, w)
    odd = ((n2 < lo) & (n2 > 0.0)) | (n2 > hi)
    if odd.any():
        w = w.copy()
        w[odd] /= np.sqrt(n2[odd])[:, None]
    return w.astype(np.float32)


def _checked_rows(z_rows, n: int, m: int, of: str) -> np.ndarray:
    """``eval_brdf``'s ``z_rows``: ``n`` integer rows of the ``m`` rows of ``of`` (z or zc), or ValueError."""
    z_rows = np.asarray(z_rows)
    if z_rows.shape != (n,) or z_rows.dtype.kind not in "iu":
        raise ValueError(f"z_rows must be {n} integer rows of {of}; got {z_rows.dtype} {z_rows.shape}")
    if n and (z_rows.min() < 0 or z_rows.max() >= m):
        raise ValueError(
            f"z_rows must index {of}'s {m} rows (integer rows 0..{m - 1}), got {z_rows.min()}..{z_rows.max()}"
        )
    return z_rows


def _latents_of_rows(z, n: int, z_rows) -> tuple[np.ndarray, bool, np.ndarray | None]:
    """``eval_brdf``'s latents for ``n`` rows: ``(z float32, per row?, z_rows)``, checked (module docstring of
    ``eval_brdf``: one (3, 32), one per row (n, 3, 32), or rows ``z_rows`` (n,) of (M, 3, 32))."""
    if np.iscomplexobj(z):
        raise ValueError("z must be real, got complex values")
    z = np.asarray(z, dtype=np.float32)
    if z_rows is not None:
        if z.ndim != 3 or z.shape[1:] != (3, LATENT):
            raise ValueError(f"z_rows reads rows of latents z (M, 3, {LATENT}), got z {z.shape}")
        return z, True, _checked_rows(z_rows, n, len(z), "z")
    if z.shape == (3, LATENT):
        return z, False, None
    if z.ndim == 3 and z.shape[1:] == (3, LATENT) and z.shape[0] == n:
        return z, True, None
    raise ValueError(f"z must have shape (3, {LATENT}) or ({n}, 3, {LATENT}) to match {n} directions, got {z.shape}")


def latents(z, name: str = "z") -> np.ndarray:
    """``z`` as float32 latents (N, 3, 32) ((3, 32) becomes (1, 3, 32)); complex, NaN or Inf raise."""
    if np.iscomplexobj(z):
        raise ValueError(f"{name} must be real, got complex values")
    z = np.asarray(z, dtype=np.float32)
    if z.shape == (3, LATENT):
        z = z[None]
    if z.ndim != 3 or z.shape[1:] != (3, LATENT):
        raise ValueError(f"{name} must have shape (N, 3, {LATENT}) or (3, {LATENT}), got {z.shape}")
    if not np.all(np.isfinite(z)):
        raise ValueError(f"{name} must be finite (the latent holds NaN or Inf)")
    return z


class ModelSet:
    """The networks of one decoder size as ONNX Runtime sessions, each checked against its card."""

    def __init__(self, size: str, threads: int = 2, model_dir: Path | str | None = None):
        if size not in SIZES:
            raise ValueError(
                f"unknown decoder size {size!r}; sizes are {list(SIZES)} (resolve 'auto' with resolve_size first)"
            )
        if isinstance(threads, bool) or int(threads) < 1:
            raise ValueError(f"threads must be >= 1, got {threads!r}")
        self.size = size
        self.threads = int(threads)
        self.model_dir = Path(model_dir) if model_dir is not None else MODEL_DIR
        self.cards: dict[str, dict] = {}
        self._sessions: dict[str, ChunkedSession] = {}
        self.decoder_path = self.path("decoder")
        self.encoder_path = self.path("encoder")
        width = self.card("decoder").get("architecture", {}).get("width")
        if width is None:
            raise ModelFileError(f"model card {self.decoder_path.stem}.json gives no architecture.width")
        chunk = max(128, DECODER_CHUNK_FLOATS // (3 * width))
        self._decoder = self._load("decoder", chunk)
        # the fused RGB graph (same weights) is faster; the scalar graph is the reference interface
        rgb = self.model_dir / f"decoder_{size}_rgb.onnx"
        self._rgb = _session(rgb, self.threads, chunk) if rgb.name in self.card("decoder")["files"] else None
        self.width = int(width)
        self._latent_graph = None  # z (B, 3, 32) -> zc (B, 3W), the fused graph's input (``project_latents``)
        if self._rgb is not None:
            latents = self.model_dir / f"decoder_{size}_latents.onnx"
            if latents.name not in self.card("decoder")["files"]:
                raise ModelFileError(
                    f"{self.decoder_path.stem}.json names {rgb.name} but not {latents.name}, which makes its input"
                )
            self._latent_graph = _session(latents, self.threads, chunk)
        self._load("encoder")
        # the decoder holds the remainder design's rest of the BRDF: eval_brdf adds the exact top lobe
        self.remainder = self.card("decoder").get("remainder", False) is True
        # ... divided by the top coat's Fresnel transmission in and out (top_lobe.remainder_scale)
        self.top_transmission = self.remainder and self.card("decoder").get("top_transmission", False) is True
        # what the renderer's materials keep of each stack they encoded with these networks, by stack
        # (``render.neural_material``): it goes with the model set, so new model files never meet an old latent
        self.encodings: OrderedDict = OrderedDict()
        self.encodings_lock = threading.Lock()

    def path(self, role: str) -> Path:
        return self.model_dir / file_name(role, self.size)

    def card(self, role: str) -> dict:
        """The checked card of one network of this size (read once)."""
        if role not in self.cards:
            self.cards[role] = read_card(role, self.size, self.model_dir)
        return self.cards[role]

    def _load(self, role: str, chunk: int | None = None) -> ChunkedSession:
        loaded = self._sessions.get(role)
        if loaded is not None:  # no wait on the lock while another thread loads something else
            return loaded
        with _LOADING:  # materials are resolved on several threads (``materials.resolve_all``): load once
            if role not in self._sessions:
                if chunk is None:  # the activations of a call in cache (DECODER_CHUNK_FLOATS)
                    width = self.card(role).get("architecture", {}).get("width") or 128
                    chunk = max(128, DECODER_CHUNK_FLOATS // (2 * int(width)))
                self.card(role)
                self._sessions[role] = _session(self.path(role), self.threads, chunk)
            return self._sessions[role]

    @property
    def projects_latents(self) -> bool:
        """Whether the decoder takes latents through :meth:`project_latents` (the fused RGB graph is shipped)."""
        return self._rgb is not None

    def project_latents(self, z) -> np.ndarray:
        """(N, 3W) float32: latents ``z`` (N, 3, 32) ((3, 32) gives one row) through the decoder's first layer, bias
        included, the three channels side by side: what its fused graph takes (``zc``), from the latent graph
        (``decoder_<size>_latents.onnx``; its time counts as the networks'). A material's latent is projected once
        a query, a latent texture's once a texel (``LatentTexture.projected``): the product is affine, so it
        commutes with the texture's filtering."""
        if not self.projects_latents:
            raise ValueError(f"decoder_{self.size} has no fused graph to take projected latents")
        z = latents(z)
        out = np.empty((len(z), 3 * self.width), dtype=np.float32)
        session = self._latent_graph

        def chunk(rows: slice) -> None:  # runs on the session's threads
            out[rows] = session.run_once(["zc"], {"z": z[rows]})[0]

        session.map(chunk, len(z))
        return out

    def load(self, *roles: str) -> "ModelSet":
        """Load (and check) the networks ``roles`` now rather than when first used; returns the set."""
        for role in roles:
            if role not in ROLES:
                raise ValueError(f"unknown network role {role!r}; roles are {list(ROLES)}")
            self._load(role)
        return self

    def has(self, role: str) -> bool:
        """Whether the network ``role`` of this size is shipped (its file exists; loading still checks it)."""
        return self.path(role).is_file()

    @property
    def digest(self) -> str:
        """Identity of the latent space: the sha256 of the decoder file (every other network's card names it)."""
        return self.card("decoder")["files"][self.decoder_path.name]

    # ------------------------------------------------------------------ the four networks

    def run_encoder(self, x: np.ndarray) -> np.ndarray:
        """Latents (N, 3, 32) of per-channel encoder features (N, 3, N_FEATURES)."""
        x = np.asarray(x, dtype=np.float32)
        if x.ndim != 3 or x.shape[1:] != (3, N_FEATURES):
            raise ValueError(f"encoder features must have shape (N, 3, {N_FEATURES}), got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError("encoder features must be finite")
        if x.shape[0] == 0:
            return np.zeros((0, 3, LATENT), dtype=np.float32)
        # Each distinct layer once (layers repeat across texels), and one channel of a layer whose
        # three channels have the same features (a dielectric interface, a grey base: no colour).
        first, inverse = distinct_rows(x.reshape(len(x), -1))
        layers = x[first]
        grey = (layers[:, 0] == layers[:, 1]).all(axis=1) & (layers[:, 0] == layers[:, 2]).all(axis=1)
        rows = np.concatenate([layers[grey, 0], layers[~grey].reshape(-1, N_FEATURES)])
        z_rows = self._load("encoder").run(["z"], {"x": rows})[0]
        z = np.empty((len(layers), 3, LATENT), dtype=np.float32)
        n_grey = int(grey.sum())
        z[grey] = z_rows[:n_grey, None, :]
        z[~grey] = z_rows[n_grey:].reshape(-1, 3, LATENT)
        return z[inverse] if len(first) < len(x) else z

    def run_layering(self, z_top, z_bottom, albedo, thickness) -> np.ndarray:
        """One application of the layering network: z_top, z_bottom (B, 32), albedo, thickness (B,) -> z (B, 32)."""
        zt = np.ascontiguousarray(z_top, dtype=np.float32)
        zb = np.ascontiguousarray(z_bottom, dtype=np.float32)
        a = np.ascontiguousarray(albedo, dtype=np.float32).reshape(-1)
        t = np.ascontiguousarray(thickness, dtype=np.float32).reshape(-1)
        b = zt.shape[0]
        if zt.shape != (b, LATENT) or zb.shape != (b, LATENT) or a.shape != (b,) or t.shape != (b,):
            raise ValueError(
                f"run_layering needs z_top, z_bottom (B, {LATENT}), albedo, thickness (B,); got "
                f"{zt.shape}, {zb.shape}, {a.shape}, {t.shape}"
            )
        session = self._load("layering")
        if b == 0:
            return np.zeros((0, LATENT), dtype=np.float32)
        return session.run(["z"], {"z_top": zt, "z_bottom": zb, "albedo": a, "thickness": t})[0]

    def proxy_params(self, z) -> np.ndarray:
        """(N, 2) float32 (sigma, w) of the sampling proxy for latents z (N, 3, 32) or (3, 32) (-> (1, 2))."""
        z = latents(z)
        session = self._load("sampling")
        if z.shape[0] == 0:
            return np.zeros((0, 2), dtype=np.float32)
        sig, w = session.run(["sigma", "w"], {"z": z})
        out = np.stack([sig, w], axis=1).astype(np.float32)
        out[:, 0] = np.maximum(out[:, 0], proxy.SIGMA_MIN)
        out[:, 1] = np.clip(out[:, 1], 0.0, 1.0)
        return out

    def eval_brdf(
        self,
        z,
        wi,
        wo,
        top=None,
        calibration=None,
        with_top_lobe=True,
        top_pdf: bool = False,
        unit: bool = False,
        z_rows=None,
        zc=None,
    ):
        """f (N, 3) in 1/sr (no cosine) for one material ``z`` (3, 32) or per-row latents (N, 3, 32); with
        ``z_rows`` (N,) the latents ``z[z_rows]`` of M (M, 3, 32), gathered a chunk at a time, not first (the
        renderer's query of a latent texture's hits: each hit's latent for its next-event and its sampled
        direction); a per-row ``top`` and calibration are then per row of ``z`` (M) as well, and read through
        ``z_rows`` too.

        ``top``: the material's top coating (alpha, ior) as (2,) or per row (N, 2; (M, 2) with ``z_rows``)
        (``top_lobe``; None or :data:`top_lobe.NO_TOP` for a stack without coatings). A remainder decoder's f is
        the decoded remainder (times the top coat's transmission for a ``top_transmission`` decoder) plus the
        exact top lobe (``with_top_lobe=False``: the remainder alone); for a whole-BRDF decoder ``top`` changes
        nothing. ``calibration`` (``calibrate.AlbedoCalibration``, or a ``calibrate.RowCalibration`` with a
        table chosen per row): its factors scale the decoded part.
        Directions need not be unit length (they are normalised; ``unit``: the caller's are unit already);
        zero-length directions and directions at or below the horizon give 0.

        ``top_pdf``: return ``(f, p)`` with ``p`` (N,) float64 the density of ``top_lobe.sample_top`` at the
        same pairs (0 without a top lobe), from the same evaluation of the lobe (the renderer's MIS needs both).

        ``zc``: the latents already through the first layer (:meth:`project_latents`; (N, 3W), or (M, 3W) with
        ``z_rows``), in place of ``z`` (None then): a projected latent texture's hits. Only with
        :attr:`projects_latents`.
        """
        wi = _directions(wi, "wi")
        wo = _directions(wo, "wo")
        if wi.shape[0] != wo.shape[0]:
            raise ValueError(f"wi has {wi.shape[0]} rows but wo has {wo.shape[0]}")
        n = wi.shape[0]
        if zc is not None:
            zc, z_rows = self._projected_rows(zc, n, z_rows)
            z, per_row = zc, True
        else:
            z, per_row, z_rows = _latents_of_rows(z, n, z_rows)
        if not np.all(np.isfinite(z)):
            raise ValueError("z must be finite (the latent holds NaN or Inf)")
        out = np.empty((n, 3), dtype=np.float32)
        if n == 0:
            return (out, np.zeros(0)) if top_pdf else out
        if self._rgb is not None:  # the graph normalises and masks the horizon itself
            # unit directions need no guard for float32's range: a cast, not the length check and its temporaries
            wi32, wo32 = (w.astype(np.float32) if unit else _float32_rows(w) for w in (wi, wo))
            zc = zc if zc is not None else self.project_latents(z)  # once a latent, not once a query row

        def latents(rows: slice, z=z) -> np.ndarray:  # np.take: 40% faster than z[z_rows[rows]] on rows
            return np.take(z, z_rows[rows], axis=0) if z_rows is not None else z[rows]

        def chunk(rows: slice) -> None:  # runs on the session's threads, one chunk of rows each
            if self._rgb is not None:
                feeds = {"zc": latents(rows, zc) if per_row else zc, "wi": wi32[rows], "wo": wo32[rows]}
                f = self._rgb.run_once(["f"], feeds)[0]
                np.fmax(f, 0.0, out=out[rows])  # fmax: NaN (an overflowing latent) gives 0
                return
            a, b = _unit_or_up(wi[rows]), _unit_or_up(wo[rows])
            m = a[0].shape[0]
            f = self._decoder.run_once(
                ["f"],
                {
                    "z": latents(rows).reshape(-1, LATENT) if per_row else np.tile(z, (m, 1)),
                    "wi": np.repeat(a[0], 3, axis=0),
                    "wo": np.repeat(b[0], 3, axis=0),
                },
            )[0].reshape(m, 3)
            # 0 below the horizon, and for NaN (an overflowing latent); the graph's exp is >= 0
            out[rows] = np.where((a[1] & b[1])[:, None] & (f >= 0.0), f, 0.0)

        (self._rgb or self._decoder).map(chunk, n)
        m = n if z_rows is None else len(z)  # the rows of per-row parameters
        t = top_lobe.top_table(top, m) if self.remainder and top is not None else None  # (1, 2): shared
        t = t if t is not None and top_lobe.has_top(t).any() else None
        if calibration is not None or t is not None:
            p_top = self._finish(out, calibration, t, wi, wo, unit, with_top_lobe, z_rows, m)
        else:
            p_top = np.zeros(n)
        return (out, p_top) if top_pdf else out

    def _projected_rows(self, zc, n: int, z_rows) -> tuple[np.ndarray, np.ndarray | None]:
        """``eval_brdf``'s ``zc`` (M, 3W) float32 with its rows ``z_rows`` (n,) (None: M = n, a row each), checked."""
        if not self.projects_latents:
            raise ValueError(f"decoder_{self.size} has no fused graph to take projected latents (zc)")
        zc = np.asarray(zc, dtype=np.float32)
        if zc.ndim != 2 or zc.shape[1] != 3 * self.width:
            raise ValueError(f"zc must be (M, {3 * self.width}) projected latents, got {zc.shape}")
        if z_rows is None:
            if len(zc) != n:
                raise ValueError(f"zc has {len(zc)} rows for {n} directions (give z_rows to read rows of it)")
            return zc, None
        return zc, _checked_rows(z_rows, n, len(zc), "zc")

    def _finish(self, out, calibration, t, wi, wo, unit: bool, with_top_lobe: bool, z_rows, m: int) -> np.ndarray:
        """``eval_brdf``'s work after the decoder, on its ``out`` in place, in one compiled pass
        (``kernels.decoded_brdf``): the calibration's factor, and for a top coat ``t`` (checked rows) the
        transmission factor of a ``top_transmission`` decoder and the exact lobe. Returns the lobe's density.
        With ``z_rows``, row i reads the coating and the table of z's row ``z_rows[i]`` (of ``m``)."""
        ui, uo = (wi, wo) if unit else (top_lobe._unit(wi), top_lobe._unit(wo))
        ui, uo = kernels.float64_rows(ui), kernels.float64_rows(uo)
        if hasattr(calibration, "check_rows"):  # a per-row choice of tables (an AlbedoCalibration has one)
            calibration.check_rows(m)
        return kernels.decoded_brdf(
            out,
            ui,
            uo,
            calibrate.NO_CALIBRATION if calibration is None else calibration.arrays(),
            top_lobe.NO_TOP_ROWS if t is None else t,
            top_lobe.transmittance_grids(),
            self.top_transmission,
            with_top_lobe,
            kernels.EVERY_ROW if z_rows is None else np.ascontiguousarray(z_rows, dtype=np.int64),
        )


_CACHE: dict[tuple[str, int, Path], ModelSet] = {}
_LOADING = threading.RLock()  # model sets and their sessions are made once, whichever thread asks first


def load_models(size: str = AUTO, threads: int = 2, model_dir: Path | str | None = None) -> ModelSet:
    """The model set of ``size`` ("auto" resolves with :func:`resolve_size`), cached per size, thread
    count and folder (the one cache of the neural runtime)."""
    size = resolve_size(size, model_dir)
    key = (size, int(threads), Path(model_dir) if model_dir is not None else MODEL_DIR)
    loaded = _CACHE.get(key)
    if loaded is not None:
        return loaded
    with _LOADING:
        if key not in _CACHE:
            _CACHE[key] = ModelSet(size, threads, model_dir)
        return _CACHE[key]


def clear_cache() -> None:
    """Forget every loaded model set (after the model files changed)."""
    _CACHE.clear()


def resolve_size(size: str = AUTO, model_dir: Path | str | None = None) -> str:
    """The decoder size a model-size setting means: a size is itself; "auto" is :data:`DEFAULT_SIZE`,
    or when its decoder and encoder are not shipped, the first size in ``SIZES`` whose are.

    Raises ValueError for anything else, FileNotFoundError when "auto" finds no shipped size."""
    if isinstance(size, str) and size.lower() in SIZES:
        return size.lower()
    if not (isinstance(size, str) and size.lower() == AUTO):
        raise ValueError(f"unknown decoder size {size!r}; sizes are {[AUTO, *SIZES]}")
    d = Path(model_dir) if model_dir is not None else MODEL_DIR
    for s in (DEFAULT_SIZE, *(x for x in SIZES if x != DEFAULT_SIZE)):
        if (d / file_name("decoder", s)).is_file() and (d / file_name("encoder", s)).is_file():
            return s
    raise FileNotFoundError(
        f"no decoder size is shipped in {d} (looked for decoder_<size>.onnx and "
        f"encoder_<size>.onnx for sizes {list(SIZES)})"
    )
