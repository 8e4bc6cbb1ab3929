"""The learned 3D patch descriptor: the CNN of the semi-dense paper (Sec. 3.3.2, Fig. 3c; Sec. 4).

A yaw-normalised patch in the CNN's cubic domain (20 x 20 x 20 m, caption of Fig. 6) becomes a
32^3 voxel grid, either binary occupancy (1 channel) or binary density comparison (3 channels,
one per axis), both made by :mod:`mapkit.places.patches`. The network (Fig. 3c): two 3D convolutions,
each followed by a ReLU, one L2 pooling layer ([32]: better than max pooling), then two fully
connected layers to a 512-dimensional descriptor. The paper gives no channel counts or kernel
sizes; ``CnnConfig`` holds mapkit's, chosen so that a training run on 2 CPU cores fits in
minutes. The descriptor is L2-normalised inside the network, so the triplet margin (Eq. 1) is
on the unit sphere and torch, ONNX and the index all see the same vector.

Two ways to run a trained model:

- torch (:func:`build_model`, :func:`load_torch_model`): training and tests; needs the
  ``learning`` extra, imported lazily so that the rest of mapkit runs without it;
- ONNX through onnxruntime (:class:`OnnxDescriber`, :func:`describe_cnn`): the deployment path
  used by ``mapkit index structure`` (kind ``cnn``) and ``mapkit eval places``; no torch.

A trained model is a folder written by :func:`mapkit.learning.train.train_cnn`: ``model.onnx``,
``model.pt`` (state dict and config) and ``manifest.json`` (form, grid, domain, checksums).
"""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from mapkit.core.config import MapkitConfig
from mapkit.core.errors import ConfigError, InputError
from mapkit.core.runio import atomic_path, sha256_file
from mapkit.places.patches import CNN_DOMAIN, PatchDomain, unpack_bits, voxel_grids, xy_tree

MODEL_FORMAT_VERSION = 1
ONNX_FILE = "model.onnx"
TORCH_FILE = "model.pt"
ONNX_INPUT, ONNX_OUTPUT = "grids", "descriptors"
ONNX_OPSET = 17

Form = Literal["occupancy", "density_comparison"]
#: input channels of each grid form (Sec. 3.3.2: occupancy 1, density comparison one per axis)
CHANNELS = {"occupancy": 1, "density_comparison": 3}

INSTALL_HINT = (
    "torch is not installed; it is an optional extra of mapkit. Install the CPU build first, "
    "`pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu` (on the project's machines "
    '`pip install torch==2.13.0` installs that CPU build offline), then `pip install -e ".[learning]"`'
)

_L2_POOL_EPS = 1e-12  # inside the square root of the L2 pooling: finite gradients where a window is all zero


class CnnConfig(MapkitConfig):
    """The architecture of Fig. 3(c). The paper fixes the input (32^3, 1 or 3 channels), the
    layer types and the 512-d output; the sizes below are mapkit's."""

    form: Form = Field(
        "occupancy",
        description="Input grid: binary occupancy (1 channel) or binary density comparison (3 channels) "
        "(Sec. 3.3.2; the paper reports both as 'barely distinguishable').",
    )
    grid: int = Field(
        32, ge=4, description="Voxels per axis (Sec. 3.3.2: 32x32x32); must match the triplet dataset's grid."
    )
    conv1_channels: int = Field(
        8,
        ge=1,
        description="Channels of the first 3D convolution (not in the paper; mapkit's choice for CPU training).",
    )
    conv1_kernel: int = Field(5, ge=1, description="Kernel of the first convolution (odd; 'same' padding).")
    conv1_stride: int = Field(2, ge=1, description="Stride of the first convolution (32^3 -> 16^3).")
    conv2_channels: int = Field(16, ge=1, description="Channels of the second 3D convolution (not in the paper).")
    conv2_kernel: int = Field(3, ge=1, description="Kernel of the second convolution (odd; stride 1, 'same' padding).")
    pool: int = Field(2, ge=1, description="Window and stride of the L2 pooling layer (Sec. 3.3.2, after [32]).")
    hidden: int = Field(512, ge=1, description="Width of the first fully connected layer (not in the paper).")
    dim: int = Field(512, ge=1, description="Descriptor dimension (Sec. 3.3.2, Fig. 3c: 512).")

    @model_validator(mode="after")
    def _check(self) -> CnnConfig:
        if self.conv1_kernel % 2 == 0 or self.conv2_kernel % 2 == 0:
            raise ValueError("convolution kernels must be odd ('same' padding)")
        if self.grid % (self.conv1_stride * self.pool):
            raise ValueError(
                f"grid {self.grid} must be a multiple of conv1_stride * pool = {self.conv1_stride * self.pool}"
            )
        return self

    @property
    def channels(self) -> int:
        return CHANNELS[self.form]

    @property
    def flat_features(self) -> int:
        """Inputs of the first fully connected layer."""
        return self.conv2_channels * (self.grid // (self.conv1_stride * self.pool)) ** 3


# --------------------------------------------------------------------------- torch, imported lazily


def require_torch():
    """The torch module, or a ConfigError saying how to install the CPU build."""
    try:
        import torch
    except ImportError:
        raise ConfigError(INSTALL_HINT) from None
    return torch


_CLASSES: dict = {}


def _module_class():
    """The nn.Module class of Fig. 3(c), defined on first use (torch imported here only)."""
    if "PatchCNN" in _CLASSES:
        return _CLASSES["PatchCNN"]
    torch = require_torch()
    nn, F = torch.nn, torch.nn.functional

    class PatchCNN(nn.Module):
        """conv - ReLU - conv - ReLU - L2 pool - FC - ReLU - FC - L2 normalisation."""

        def __init__(self, cfg: CnnConfig):
            super().__init__()
            self.pool = cfg.pool
            self.conv1 = nn.Conv3d(
                cfg.channels, cfg.conv1_channels, cfg.conv1_kernel, cfg.conv1_stride, cfg.conv1_kernel // 2
            )
            self.conv2 = nn.Conv3d(cfg.conv1_channels, cfg.conv2_channels, cfg.conv2_kernel, 1, cfg.conv2_kernel // 2)
            self.fc1 = nn.Linear(cfg.flat_features, cfg.hidden)
            self.fc2 = nn.Linear(cfg.hidden, cfg.dim)

        def forward(self, x):
            x = F.relu(self.conv1(x))
            x = F.relu(self.conv2(x))
            # L2 pooling: the 2-norm of each window, sqrt(sum x^2) = sqrt(mean x^2 * window volume)
            x = torch.sqrt(F.avg_pool3d(x * x, self.pool) * float(self.pool**3) + _L2_POOL_EPS)
            x = F.relu(self.fc1(torch.flatten(x, 1)))
            return F.normalize(self.fc2(x), dim=1)

    _CLASSES["PatchCNN"] = PatchCNN
    return PatchCNN


def build_model(cfg: CnnConfig | None = None, seed: int | None = None):
    """A new (untrained) network; ``seed`` fixes its initial weights."""
    torch = require_torch()
    cfg = cfg or CnnConfig()
    if seed is not None:
        torch.manual_seed(seed)
    return _module_class()(cfg)


def triplet_loss(d1, d2, d3, margin: float):
    """Eq. (1) of the semi-dense paper, averaged over the batch:
    ``L = max(||D(X1) - D(X2)|| + m - ||D(X1) - D(X3)||, 0)^2`` for descriptor batches (B, D)."""
    torch = require_torch()
    pos = torch.linalg.vector_norm(d1 - d2, dim=1)
    neg = torch.linalg.vector_norm(d1 - d3, dim=1)
    return torch.clamp(pos + margin - neg, min=0.0).pow(2).mean()


def grids_to_input(grids: np.ndarray, form: Form) -> np.ndarray:
    """float32 network input (n, C, g, g, g) of unpacked 0/1 grids: (n, g, g, g) occupancy or
    (n, 3, g, g, g) density comparison."""
    g = np.asarray(grids)
    if form == "occupancy":
        if g.ndim != 4:
            raise InputError(None, f"occupancy grids must be (n, g, g, g), got {g.shape}", field="grids")
        g = g[:, None]
    elif g.ndim != 5 or g.shape[1] != 3:
        raise InputError(None, f"density-comparison grids must be (n, 3, g, g, g), got {g.shape}", field="grids")
    return g.astype(np.float32)


def torch_describe(model, grids: np.ndarray, form: Form, batch: int = 256) -> np.ndarray:
    """(n, dim) float32 descriptors of unpacked grids with a torch model (no gradients)."""
    torch = require_torch()
    out = []
    was_training = model.training
    model.eval()
    with torch.no_grad():
        for k in range(0, len(grids), batch):
            out.append(model(torch.from_numpy(grids_to_input(grids[k : k + batch], form))).numpy())
    model.train(was_training)
    dim = model.fc2.out_features
    return np.concatenate(out).astype(np.float32) if out else np.zeros((0, dim), np.float32)


def export_onnx(model, cfg: CnnConfig, path: str | Path) -> Path:
    """Write ``model`` as ONNX (opset 17, batch axis dynamic), atomically. Uses torch's
    TorchScript-based exporter (``dynamo=False``): the dynamo one needs onnxscript, not a
    dependency of mapkit."""
    torch = require_torch()
    import warnings

    path = Path(path)
    was_training = model.training
    model.eval()
    example = torch.zeros((2, cfg.channels, cfg.grid, cfg.grid, cfg.grid), dtype=torch.float32)
    with atomic_path(path) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exporter's deprecation notices
        torch.onnx.export(
            model,
            (example,),
            str(tmp),
            dynamo=False,
            input_names=[ONNX_INPUT],
            output_names=[ONNX_OUTPUT],
            dynamic_axes={ONNX_INPUT: {0: "n"}, ONNX_OUTPUT: {0: "n"}},
            opset_version=ONNX_OPSET,
        )
    model.train(was_training)
    return path


def load_torch_model(folder: str | Path):
    """(model, CnnConfig) of a trained model folder's ``model.pt``."""
    torch = require_torch()
    p = Path(folder) / TORCH_FILE
    if not p.is_file():
        raise InputError(p, "no such file (not a trained CNN folder? see mapkit train)")
    blob = torch.load(p, map_location="cpu", weights_only=True)
    cfg = CnnConfig.model_validate(blob["model_config"])
    model = _module_class()(cfg)
    model.load_state_dict(blob["state_dict"])
    model.eval()
    return model, cfg


# --------------------------------------------------------------------------- deployment: ONNX, no torch


def read_model_manifest(folder: str | Path) -> dict:
    """The manifest of a trained model folder, checked: format version and the ONNX file's sha256."""
    folder = Path(folder)
    mpath = folder / "manifest.json"
    if not mpath.is_file():
        raise InputError(
            folder, "not a trained CNN folder (no manifest.json; train one with mapkit train)", field="cnn_model"
        )
    m = json.loads(mpath.read_text())
    if m.get("format_version") != MODEL_FORMAT_VERSION or m.get("kind") != "mapkit cnn descriptor":
        raise InputError(mpath, f"not a CNN model manifest of format {MODEL_FORMAT_VERSION}", field="format_version")
    onnx_info = (m.get("files") or {}).get(ONNX_FILE)
    if onnx_info is None or not (folder / ONNX_FILE).is_file():
        raise InputError(folder / ONNX_FILE, "missing (the model folder has no ONNX export)")
    if sha256_file(folder / ONNX_FILE) != onnx_info["sha256"]:
        raise InputError(
            folder / ONNX_FILE, "checksum mismatch: the file changed since the model was written", field="sha256"
        )
    return m


class OnnxDescriber:
    """A trained model run by onnxruntime: voxel grids -> L2-normalised float32 descriptors."""

    def __init__(self, folder: str | Path, threads: int | None = None):
        import onnxruntime as ort

        self.folder = Path(folder)
        self.manifest = read_model_manifest(self.folder)
        self.sha256 = self.manifest["files"][ONNX_FILE]["sha256"]
        self.cfg = CnnConfig.model_validate(self.manifest["model_config"])
        self.domain = PatchDomain.model_validate(self.manifest["domain"])
        opts = ort.SessionOptions()
        if threads:
            opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
        self.session = ort.InferenceSession(str(self.folder / ONNX_FILE), opts, providers=["CPUExecutionProvider"])

    def describe_grids(self, grids: np.ndarray, batch: int = 256) -> np.ndarray:
        """(n, dim) descriptors of unpacked grids ((n, g, g, g) or (n, 3, g, g, g), 0/1)."""
        out = [
            self.session.run([ONNX_OUTPUT], {ONNX_INPUT: grids_to_input(grids[k : k + batch], self.cfg.form)})[0]
            for k in range(0, len(grids), batch)
        ]
        return np.concatenate(out).astype(np.float32) if out else np.zeros((0, self.cfg.dim), np.float32)

    def describe(
        self, points: np.ndarray, keypoints: np.ndarray, observer_dirs: np.ndarray, tree=None, batch: int = 256
    ) -> np.ndarray:
        """(M, dim) descriptors of the patches about ``keypoints`` (M, 3) in the cloud ``points``:
        extracted in the model's cubic domain, yaw-normalised towards ``observer_dirs`` (from
        keypoint to first observer, Sec. 3.2), voxelised (Sec. 3.3.2), run in batches."""
        kp = np.asarray(keypoints, np.float64).reshape(-1, 3)
        if len(kp) == 0:
            return np.zeros((0, self.cfg.dim), np.float32)
        pts = np.asarray(points, np.float64)
        tree = xy_tree(pts) if tree is None else tree
        dirs = np.asarray(observer_dirs, np.float64).reshape(len(kp), -1)
        out = np.empty((len(kp), self.cfg.dim), np.float32)
        g = self.cfg.grid
        for k0 in range(0, len(kp), batch):  # grids packed per block: 16 KiB a patch instead of 128
            k1 = min(k0 + batch, len(kp))
            occ, dcg, _ = voxel_grids(pts, kp[k0:k1], dirs[k0:k1], self.domain, g, tree, packed=True)
            grids = unpack_bits(occ if self.cfg.form == "occupancy" else dcg, g)
            out[k0:k1] = self.describe_grids(grids, batch)
        return out


_DESCRIBER_CACHE: dict[tuple[str, float], OnnxDescriber] = {}
_CACHE_LOCK = threading.Lock()


def onnx_describer(folder: str | Path) -> OnnxDescriber:
    """The OnnxDescriber of a model folder, loaded once per process (and again when the ONNX file changes)."""
    folder = Path(folder).resolve()
    key = (str(folder), (folder / ONNX_FILE).stat().st_mtime if (folder / ONNX_FILE).is_file() else 0.0)
    with _CACHE_LOCK:
        if key not in _DESCRIBER_CACHE:
            _DESCRIBER_CACHE[key] = OnnxDescriber(folder)
        return _DESCRIBER_CACHE[key]


def describe_cnn(points: np.ndarray, keypoints: np.ndarray, observer_dirs: np.ndarray, cfg, tree=None) -> np.ndarray:
    """The structure index's describer of kind ``cnn`` (``mapkit.places.index_structure._describe``):
    runs the ONNX model of ``cfg.cnn_model``."""
    if getattr(cfg, "cnn_model", None) is None:
        raise ConfigError(
            "the cnn descriptor needs a trained model: set structure index config cnn_model to a mapkit train output "
            "folder"
        )
    return onnx_describer(cfg.cnn_model).describe(points, keypoints, observer_dirs, tree)


def model_fingerprint(folder: str | Path) -> dict:
    """What an index records of the model it was built with: folder, ONNX sha256, form, grid,
    domain, training dataset and epochs (from the model's manifest)."""
    m = read_model_manifest(folder)
    return {
        "path": str(Path(folder).resolve()),
        "onnx_sha256": m["files"][ONNX_FILE]["sha256"],
        "config_hash": m.get("config_hash"),
        "form": m["model_config"]["form"],
        "grid": m["model_config"]["grid"],
        "domain": m["domain"],
        "dataset": m.get("dataset", {}).get("path"),
        "epochs": m.get("epochs"),
        "hard_negatives": m.get("hard_negatives"),
    }


__all__ = [
    "CnnConfig",
    "CHANNELS",
    "INSTALL_HINT",
    "require_torch",
    "build_model",
    "triplet_loss",
    "grids_to_input",
    "torch_describe",
    "export_onnx",
    "load_torch_model",
    "read_model_manifest",
    "OnnxDescriber",
    "onnx_describer",
    "describe_cnn",
    "model_fingerprint",
    "CNN_DOMAIN",
]
