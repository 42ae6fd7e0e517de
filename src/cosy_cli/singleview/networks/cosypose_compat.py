"""CosyPose's published networks in cosy: run directories, the network, and the original stage-1 path.

CosyPose (Labbé et al. 2020) published its coarse and refiner networks as *run directories*
(``config.yaml`` + ``checkpoint.pth.tar``). This module reads them without the original code and
reproduces, on a CPU, exactly what the original ``PosePredictor`` does with them (the fixture
``../shared/fixtures/cosypose_networks`` and ``tests/test_cosypose_networks.py`` check every
step against the original's own outputs):

* :func:`read_run` parses ``config.yaml`` (a YAML-dumped ``argparse.Namespace`` with python tags)
  with a *safe* loader that maps the tags to plain data, and :func:`load_state_dict` reads the
  legacy torch checkpoint (CUDA storages) on the CPU, weights only;
* :class:`CosyPoseNet` rebuilds the network: EfficientNet-B3 (``efficientnet_pytorch``) with the
  original's static "same" padding computed for a 300-px image, BN eps 1e-3, 6 input channels,
  mean pooling and ``pose_fc`` 1536 -> 9. Input (B, 6, 240, 320) float32 = [image crop RGB,
  render RGB] in [0, 1] (no normalisation), output (B, 9) raw: ortho6d (6), v_x, v_y (px), v_z;
  :func:`export_onnx` writes it as one ONNX file with a model card, :class:`OnnxCosyPoseNet` runs it;
* :class:`MeshPoints` gives the 2,000 "deterministic" points the original samples from its mesh
  database (trimesh 3.5.16 vertex order, padding over the object set, one shared index set);
* :func:`crop_boxes`, :func:`K_crop_resize`, :func:`roi_align`, :func:`ortho6d_to_matrix`,
  :func:`update_poses`, :func:`init_poses`: the crop (centred on the projected object origin,
  lambda 1.4, the input image's aspect, ``roi_align(aligned=False, sampling_ratio=4)``), the cropped
  intrinsics, the update and the coarse initialisations ('z-up+auto-depth' and 'v0');
* :class:`CosyPoseRenderAndCompare` chains them with cosy's renderer (meshes with their own
  colours/textures, black background, the original's object-fixed light) for ``cosy estimate``.

Units: cosy's house units. Poses T_cam_obj (4, 4) with translations in **mm** (the original works
in metres; every step is scale-invariant except two constants, scaled here: the projection's
z_min 0.1 m = 100 mm and the 'v0' depth 1 m = 1000 mm). Boxes (x1, y1, x2, y2) px, K with pixel
centres at integer coordinates, images RGB.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ...errors import CosyError

CONFIG_NAME = "config.yaml"
CHECKPOINT_NAME = "checkpoint.pth.tar"
CROP_HW = (240, 320)  # the network input (height, width) px, fixed in the original
LAMBDA = 1.4  # crop enlargement (DeepIM)
N_POINTS = 2000  # points sampled from the mesh database for boxes and the coarse init
Z_MIN_MM = 100.0  # project_points_robust's z_min (0.1 m)
V0_DEPTH_MM = 1000.0  # TCO_init_from_boxes: z = 1 m
SAMPLING_RATIO = 4  # roi_align
EFFNET_IMAGE_SIZE = 300  # the static padding of efficientnet-b3 is computed for this size
INIT_METHODS = ("z-up+auto-depth", "v0")
ZUP_ROTATION = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])
# The original renders with pybullet, the object at the world origin (TWO = identity) and the
# camera at TOC: pybullet's default light (direction (-50, 30, 100) in the world for its default
# z-up axis) is therefore fixed in the *object* frame. Shadows and the specular term of pybullet's
# shader are not reproduced (see docs/cosypose.md).
LIGHT_POS_OBJ = np.array([-50.0, 30.0, 100.0])
RENDER_AMBIENT = 0.4  # our approximation of pybullet's ambient + diffuse split (see docs/cosypose.md)
METADATA_KEY = "cosypose_network"
INPUT_NAME = "input"
OUTPUT_NAME = "pose"
OPSET = 17

# object_ds_name of a CosyPose config -> the BOP models folder it loads (datasets_cfg.make_object_dataset)
OBJECT_DS_MODELS = {
    "ycbv.bop": "ycbv/models", "ycbv.bop-compat": "ycbv/models_bop-compat",
    "ycbv.bop-compat.eval": "ycbv/models_bop-compat_eval", "tless.cad": "tless/models_cad",
    "tless.eval": "tless/models_eval", "tless.bop": "tless/models_eval", "hb": "hb/models",
    "icbin": "icbin/models", "itodd": "itodd/models", "lm": "lm/models", "tudl": "tudl/models",
}


# ------------------------------------------------------------------------------------------------
# run directories
# ------------------------------------------------------------------------------------------------
def _safe_loader():
    import yaml

    class Loader(yaml.SafeLoader):
        """SafeLoader + the three python tags of CosyPose configs, as plain data (no objects built)."""

    def namespace(loader, node):
        return loader.construct_mapping(node, deep=True)

    def tuple_(loader, node):
        return list(loader.construct_sequence(node, deep=True))

    def path(loader, node):
        parts = [str(p) for p in loader.construct_sequence(node, deep=True)]
        if not parts:
            return ""
        head = parts[0]
        return head + "/".join(parts[1:]) if head.endswith("/") else "/".join(parts)

    def refuse(loader, suffix, node):
        raise CosyError(f"config.yaml: unsupported python tag {node.tag!r} (only argparse.Namespace, tuple and "
                        "pathlib paths are read; nothing else is constructed)")

    Loader.add_constructor("tag:yaml.org,2002:python/object:argparse.Namespace", namespace)
    Loader.add_constructor("tag:yaml.org,2002:python/tuple", tuple_)
    for p in ("PosixPath", "WindowsPath", "PurePosixPath", "Path"):
        Loader.add_constructor(f"tag:yaml.org,2002:python/object/apply:pathlib.{p}", path)
    Loader.add_multi_constructor("tag:yaml.org,2002:python/", refuse)
    Loader.add_multi_constructor("!", refuse)
    return Loader


def load_config(path: str | Path) -> dict:
    """A CosyPose ``config.yaml`` as a plain dict (Namespace -> mapping, tuple -> list,
    PosixPath -> str), read safely: no other python tag is accepted."""
    import yaml

    path = Path(path)
    try:
        data = yaml.load(path.read_text(), Loader=_safe_loader())  # noqa: S506 (a SafeLoader subclass)
    except CosyError as e:
        raise CosyError(e.detail, path=path) from None
    except yaml.YAMLError as e:
        raise CosyError(f"not a readable YAML file: {str(e).splitlines()[0]}", path=path) from None
    if not isinstance(data, dict):
        raise CosyError("expected a mapping (a dumped argparse.Namespace)", path=path)
    return data


@dataclass
class CosyPoseRun:
    """What cosy reads from a CosyPose run directory (only the fields the original loaders read).

    kind: "coarse" or "refiner" (``train_refiner``); init_method: the coarse initialisation
    ('z-up+auto-depth' or 'v0', default 'v0' when missing, as ``check_update_config``);
    backbone (efficientnet-b3), n_pose_dims (9), object_ds_name / urdf_ds_name (the object set it
    was trained on), run_id, config: the whole parsed config.
    """

    run_dir: Path
    kind: str
    init_method: str
    backbone: str
    n_pose_dims: int
    object_ds_name: str | None
    urdf_ds_name: str | None
    run_id: str
    config: dict = field(repr=False)

    def card(self) -> dict:
        """The fields that go into ONNX metadata and the model card."""
        return {"format": "cosypose", "kind": self.kind, "init_method": self.init_method, "backbone": self.backbone,
                "n_pose_dims": self.n_pose_dims, "object_ds_name": self.object_ds_name,
                "urdf_ds_name": self.urdf_ds_name, "run_id": self.run_id, "input": [6, CROP_HW[0], CROP_HW[1]],
                "models_folder": OBJECT_DS_MODELS.get(str(self.object_ds_name))}


def is_cosypose_run(path: str | Path) -> bool:
    """Whether ``path`` is a directory with a CosyPose ``config.yaml`` and ``checkpoint.pth.tar``."""
    p = Path(path)
    return p.is_dir() and (p / CONFIG_NAME).is_file() and (p / CHECKPOINT_NAME).is_file()


def read_run(run_dir: str | Path) -> CosyPoseRun:
    """Parse a CosyPose run directory; :class:`CosyError` naming what is missing or wrong."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise CosyError("run directory not found", path=run_dir)
    missing = [n for n in (CONFIG_NAME, CHECKPOINT_NAME) if not (run_dir / n).is_file()]
    if missing:
        raise CosyError(f"not a CosyPose run directory: {' and '.join(missing)} missing (a published CosyPose run "
                        f"has {CONFIG_NAME} and {CHECKPOINT_NAME})", path=run_dir)
    cfg = load_config(run_dir / CONFIG_NAME)
    where = run_dir / CONFIG_NAME
    for key in ("backbone_str", "n_pose_dims"):
        if key not in cfg:
            raise CosyError(f"config has no '{key}' (not a CosyPose pose-network run?)", path=where)
    if "train_refiner" in cfg:
        refiner = bool(cfg["train_refiner"])
    elif "TCO_input_generator" in cfg:
        refiner = cfg["TCO_input_generator"] == "gt+noise"
    else:
        raise CosyError("config has neither 'train_refiner' nor 'TCO_input_generator': cannot tell coarse from "
                        "refiner", path=where)
    init = cfg.get("init_method") or "v0"
    if init not in INIT_METHODS:
        raise CosyError(f"init_method {init!r} is not one of {', '.join(INIT_METHODS)}", path=where)
    backbone = str(cfg["backbone_str"])
    if not re.fullmatch(r"efficientnet-b[0-7]", backbone):
        raise CosyError(f"backbone_str {backbone!r}: only EfficientNet backbones are supported", path=where)
    n_dims = int(cfg["n_pose_dims"])
    if n_dims != 9:
        raise CosyError(f"n_pose_dims {n_dims}: only the 9-dimensional update (ortho6d + vx, vy, vz) is "
                        "supported", path=where)
    return CosyPoseRun(run_dir=run_dir, kind="refiner" if refiner else "coarse", init_method=str(init),
                       backbone=backbone, n_pose_dims=n_dims, object_ds_name=cfg.get("object_ds_name"),
                       urdf_ds_name=cfg.get("urdf_ds_name"), run_id=str(cfg.get("run_id") or run_dir.name),
                       config=cfg)


def load_state_dict(path: str | Path) -> dict:
    """``checkpoint.pth.tar`` -> its ``state_dict`` (CPU tensors), weights only (no code runs)."""
    path = Path(path)
    try:
        ckpt = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types on bad files
        raise CosyError(f"cannot read checkpoint ({type(e).__name__}: {str(e).splitlines()[0][:200]})",
                        path=path) from None
    sd = ckpt.get("state_dict", ckpt) if isinstance(ckpt, dict) else None
    if not isinstance(sd, dict) or not sd:
        raise CosyError("checkpoint has no 'state_dict'", path=path)
    return {(k[len("module."):] if k.startswith("module.") else k): v for k, v in sd.items()}


# ------------------------------------------------------------------------------------------------
# the network
# ------------------------------------------------------------------------------------------------
def _static_same_padding(kernel: int, stride: int, size: int = EFFNET_IMAGE_SIZE) -> tuple[int, int]:
    """TF-'same' padding (before, after) of one side for an input of ``size`` px."""
    out = math.ceil(size / stride)
    pad = max((out - 1) * stride + kernel - size, 0)
    return pad // 2, pad - pad // 2


def build_backbone(name: str = "efficientnet-b3", in_channels: int = 6) -> nn.Module:
    """EfficientNet as CosyPose builds it: ``efficientnet_pytorch`` weights layout, no classifier,
    every convolution padded for the model's nominal image size (300 px for B3) whatever the input
    (the original's copy of the library keeps one image size for all layers; the installed one
    shrinks it per stage, which gives other paddings at strided 5x5 convolutions)."""
    from efficientnet_pytorch import EfficientNet
    from efficientnet_pytorch.utils import Conv2dStaticSamePadding

    net = EfficientNet.from_name(name, in_channels=in_channels, include_top=False)
    size = int(net._global_params.image_size)
    for m in net.modules():
        if isinstance(m, Conv2dStaticSamePadding):
            ph = _static_same_padding(m.kernel_size[0], m.stride[0], size)
            pw = _static_same_padding(m.kernel_size[1], m.stride[1], size)
            m.static_padding = nn.ZeroPad2d((pw[0], pw[1], ph[0], ph[1])) if any(ph + pw) else nn.Identity()
    net.set_swish(memory_efficient=False)  # plain x * sigmoid(x): same values, traceable
    return net


class CosyPoseNet(nn.Module):
    """CosyPose's PosePredictor network: backbone -> mean over the feature map -> pose_fc (9).

    forward(x): x (B, 6, 240, 320) float32 = [image crop RGB, render RGB] in [0, 1] -> (B, 9)
    raw outputs (ortho6d, v_x, v_y px, v_z). State-dict keys are the original's
    (``backbone.*``, ``pose_fc.*``)."""

    def __init__(self, backbone: str = "efficientnet-b3", n_pose_dims: int = 9):
        super().__init__()
        self.backbone = build_backbone(backbone, in_channels=6)
        self.pose_fc = nn.Linear(self.backbone._conv_head.out_channels, n_pose_dims, bias=True)

    def feature_map(self, x: torch.Tensor) -> torch.Tensor:
        return self.backbone.extract_features(x)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 1536) pooled features: the input of pose_fc."""
        return self.feature_map(x).flatten(2).mean(-1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.pose_fc(self.features(x))


def load_network(run: CosyPoseRun | str | Path) -> CosyPoseNet:
    """The network of a CosyPose run directory, weights loaded strictly, in eval mode (CPU)."""
    run = run if isinstance(run, CosyPoseRun) else read_run(run)
    sd = load_state_dict(run.run_dir / CHECKPOINT_NAME)
    net = CosyPoseNet(run.backbone, run.n_pose_dims)
    try:
        net.load_state_dict(sd, strict=True)
    except RuntimeError as e:
        raise CosyError(f"checkpoint does not match a {run.backbone} CosyPose network: "
                        f"{str(e).splitlines()[0][:300]}", path=run.run_dir / CHECKPOINT_NAME) from None
    return net.eval()


class _CardNet:
    """What both runners say about their network (from its model card)."""

    card: dict

    @property
    def kind(self) -> str:
        return self.card["kind"]

    @property
    def init_method(self) -> str:
        return self.card["init_method"]


class TorchCosyPoseNet(_CardNet):
    """A run directory run with torch (no export): ``net(x)`` (B, 6, 240, 320) -> (B, 9) numpy."""

    def __init__(self, run: CosyPoseRun | str | Path, device: str = "cpu"):
        self.run = run if isinstance(run, CosyPoseRun) else read_run(run)
        self.card = self.run.card()
        self.device = device
        self.module = load_network(self.run).to(device)
        self.path = self.run.run_dir

    def __call__(self, x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return self.module(torch.as_tensor(np.ascontiguousarray(x, dtype=np.float32),
                                               device=self.device)).cpu().numpy()


def export_onnx(run_dir: str | Path, out: str | Path, opset: int = OPSET, log=print) -> Path:
    """Export a CosyPose run's network to ``out`` (one ONNX file, dynamic batch, input ``input``
    (B, 6, 240, 320), output ``pose`` (B, 9) raw) and write the model card ``out``.md."""
    import warnings

    from ...io.atomic import atomic_path, write_text
    from .onnx import stamp_card

    run = read_run(run_dir)
    net = load_network(run)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    dummy = torch.rand(2, 6, *CROP_HW)
    with atomic_path(out) as tmp:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(net, (dummy,), str(tmp), input_names=[INPUT_NAME], output_names=[OUTPUT_NAME],
                              dynamic_axes={INPUT_NAME: {0: "batch"}, OUTPUT_NAME: {0: "batch"}},
                              opset_version=opset, dynamo=False, external_data=False)
        stamp_card(tmp, METADATA_KEY, run.card())
    write_text(out.with_suffix(".md"), model_card(run, out))
    log(f"export: CosyPose {run.kind} network of run {run.run_id} ({run.backbone}, init {run.init_method}, "
        f"objects {run.object_ds_name}) -> {out}")
    return out


def model_card(run: CosyPoseRun, onnx_path: Path) -> str:
    c = run.card()
    models = c["models_folder"] or "(unknown object set: use the BOP models the run was trained on)"
    return "\n".join([
        f"# CosyPose {run.kind} network: {run.run_id}", "",
        "Exported by `cosy export --run` from a CosyPose run directory (published checkpoint format).", "",
        "| field | value |", "| --- | --- |",
        f"| kind | {run.kind} |",
        f"| init method (coarse initialisation; read from coarse runs only) | {run.init_method} |",
        f"| backbone | {run.backbone}, 6 input channels, static padding for 300 px, BN eps 1e-3 |",
        f"| object set (object_ds_name / urdf_ds_name) | {run.object_ds_name} / {run.urdf_ds_name} |",
        f"| meshes it expects | BOP `{models}` |",
        f"| input `{INPUT_NAME}` | (B, 6, 240, 320) float32: image crop RGB, render RGB, in [0, 1], no normalisation |",
        f"| output `{OUTPUT_NAME}` | (B, 9) raw: ortho6d (6), v_x, v_y (px in the crop), v_z (relative depth) |",
        f"| source | {run.run_dir.resolve()} |",
        f"| file | {onnx_path.name} |", "",
        "Run it with `cosy estimate --coarse COARSE.onnx --refiner REFINER.onnx ...` (the CosyPose crop, update "
        "and initialisation are applied).", "",
    ])


class OnnxCosyPoseNet(_CardNet):
    """An ONNX file written by :func:`export_onnx`, run by onnxruntime: ``net(x)`` -> (B, 9)."""

    def __init__(self, path: str | Path, providers: list[str] | None = None, threads: int | None = None):
        from ...onnxrt import open_session

        self.session, self.card = open_session(path, METADATA_KEY, providers, threads,
                                               not_ours="not a CosyPose network exported by `cosy export --run`")
        self.path = Path(path)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float32)
        if x.ndim != 4 or x.shape[1:] != (6,) + CROP_HW:
            raise ValueError(f"CosyPose network expects (B, 6, {CROP_HW[0]}, {CROP_HW[1]}), got {x.shape}")
        return self.session.run([OUTPUT_NAME], {INPUT_NAME: x})[0]


def is_cosypose_onnx(path: str | Path) -> bool:
    """Whether ``path`` is an ONNX file exported by :func:`export_onnx` (reads only its metadata)."""
    p = Path(path)
    if not p.is_file() or p.suffix.lower() != ".onnx":
        return False
    try:
        import onnx

        m = onnx.load(str(p), load_external_data=False)
    except Exception:  # not an ONNX file: the caller reports it
        return False
    return any(e.key == METADATA_KEY for e in m.metadata_props)


def is_cosypose_model(path) -> bool:
    return path is not None and (is_cosypose_run(path) or is_cosypose_onnx(path))


def model_sha1(path: str | Path) -> str:
    """sha1 of a model file, or of a CosyPose run directory (its config and checkpoint)."""
    import hashlib

    from ...io.cache import file_sha1

    p = Path(path)
    if not p.is_dir():
        return file_sha1(p)
    h = hashlib.sha1()
    for name in (CONFIG_NAME, CHECKPOINT_NAME):
        h.update(file_sha1(p / name).encode())
    return h.hexdigest()


def make_runner(path: str | Path, kind: str, db, renderer, providers: list[str] | None = None,
                batch_size: int = 32) -> "CosyPoseRenderAndCompare":
    """The stage-1 runner of a CosyPose network (run directory or exported ONNX) for the objects of
    ``db`` (an ObjectDatabase read from a BOP models folder) rendered by ``renderer``."""
    net = open_network(path, providers)
    if net.kind != kind:
        raise CosyError(f"expected a CosyPose {kind} network, this one is a {net.kind} network", path=path)
    if db.models_dir is None:
        raise CosyError("CosyPose networks need the BOP models folder (its models_info.json order)")
    return CosyPoseRenderAndCompare(net, renderer, MeshPoints.from_models_dir(db.models_dir), batch_size=batch_size)


def open_network(path: str | Path, providers: list[str] | None = None):
    """A CosyPose network from a run directory (torch) or an exported ONNX file (onnxruntime)."""
    p = Path(path)
    if p.is_dir():
        return TorchCosyPoseNet(p, device="cuda" if providers and "CUDAExecutionProvider" in providers
                                and torch.cuda.is_available() else "cpu")
    return OnnxCosyPoseNet(p, providers=providers)


# ------------------------------------------------------------------------------------------------
# the mesh database's points
# ------------------------------------------------------------------------------------------------
def trimesh3516_vertex_order(vertices_mm: np.ndarray, normals: np.ndarray | None = None,
                             uv: np.ndarray | None = None) -> np.ndarray:
    """The file indices of the vertices trimesh 3.5.16 keeps on load (``merge_vertices``), in its
    order: rows (V*1e8, N*1e2, UV*1e4) rounded to int64, wrapped to int32, sorted by their raw bytes,
    duplicates collapsed to their first occurrence."""
    cols = [np.asarray(vertices_mm, dtype=np.float64) * 1e8]
    if normals is not None:
        cols.append(np.asarray(normals, dtype=np.float64) * 1e2)
    if uv is not None:
        cols.append(np.asarray(uv, dtype=np.float64) * 1e4)
    st = np.ascontiguousarray(np.column_stack(cols).round().astype(np.int64).astype(np.int32))
    rows = st.view(np.dtype((np.void, st.dtype.itemsize * st.shape[1]))).reshape(-1)
    _, first = np.unique(rows, return_index=True)
    return first


def original_vertices(ply_path: str | Path) -> np.ndarray:
    """(n, 3) mm: the vertices of a BOP PLY in the order CosyPose's mesh database holds them."""
    import trimesh

    mesh = trimesh.load(str(ply_path), force="mesh", process=False)
    V = np.asarray(mesh.vertices, dtype=np.float64)
    raw = (mesh.metadata or {}).get("_ply_raw", {}).get("vertex", {}).get("data")
    names = raw.dtype.names if raw is not None and raw.dtype.names else ()
    N = np.column_stack([raw[k] for k in ("nx", "ny", "nz")]).astype(np.float64) \
        if all(k in names for k in ("nx", "ny", "nz")) else None
    uv = getattr(mesh.visual, "uv", None) if mesh.visual.kind == "texture" else None
    order = trimesh3516_vertex_order(V, N, None if uv is None else np.asarray(uv, dtype=np.float64))
    used = np.zeros(len(V), bool)
    used[np.asarray(mesh.faces).reshape(-1)] = True
    order = order[used[order]]  # unreferenced vertices are dropped (relative order kept)
    return V[order]


class MeshPoints:
    """The original's ``mesh_db.select(labels).sample_points(2000, deterministic=True)``.

    vertices: label -> (n, 3) mm in database order (:func:`original_vertices`). Every object is
    padded to the largest vertex count with rows drawn by one shared ``RandomState(0)`` over the
    objects in database order; then one index set ``RandomState(0).choice(n_max, 2000,
    replace=False)`` is used for all objects.
    """

    def __init__(self, vertices: dict, n_points: int = N_POINTS):
        self.labels = list(vertices)
        n_max = max(len(v) for v in vertices.values())
        if n_max < n_points:
            raise CosyError(f"the original samples {n_points} mesh vertices, but the largest mesh of this object "
                            f"set has only {n_max}")
        rs = np.random.RandomState(0)
        self.padded = {}
        for label, v in vertices.items():
            v = np.asarray(v, dtype=np.float64)
            if len(v) < n_max:
                ids = rs.choice(np.arange(len(v)), size=n_max - len(v))
                v = np.concatenate([v, v[ids]])
            self.padded[label] = v
        self.n_max = n_max
        self.sample_ids = np.random.RandomState(0).choice(n_max, n_points, replace=False)
        self.points = {k: v[self.sample_ids] for k, v in self.padded.items()}

    @classmethod
    def from_models_dir(cls, models_dir: str | Path) -> "MeshPoints":
        """Objects in the order of ``models_info.json`` (the order BOPObjectDataset reads), keyed by
        integer obj_id."""
        models_dir = Path(models_dir)
        info_path = models_dir / "models_info.json"
        if not info_path.is_file():
            raise CosyError("models_info.json missing", path=info_path)
        keys = list(json.loads(info_path.read_text()))
        verts = {}
        for k in keys:
            p = models_dir / f"obj_{int(k):06d}.ply"
            if not p.is_file():
                raise CosyError(f"model of object {k} listed in models_info.json is missing", path=p)
            verts[int(k)] = original_vertices(p)
        return cls(verts)

    def select(self, labels) -> np.ndarray:
        """(B, 2000, 3) mm for labels (B,)."""
        return np.stack([self.points[lab] for lab in labels])


# ------------------------------------------------------------------------------------------------
# geometry of the original path (numpy, batched)
# ------------------------------------------------------------------------------------------------
# These three run in float32 torch, in metres, with the original's operation order, so that boxes
# and cropped intrinsics are bit-identical to the original's (float64 differs by float32 round-off,
# up to 1e-4 px, which moves sharp edges of the crops by as much).
def _f32_m(points_mm, K, T_mm):
    pts = torch.as_tensor(np.asarray(points_mm, np.float64) * 1e-3, dtype=torch.float32)
    T = np.array(T_mm, np.float64)
    T[..., :3, 3] *= 1e-3
    return pts, torch.as_tensor(np.array(K, np.float64), dtype=torch.float32), torch.as_tensor(T, dtype=torch.float32)


def _project_f32(pts: torch.Tensor, K: torch.Tensor, T: torch.Tensor, z_min: float) -> torch.Tensor:
    P = (K @ T[:, :3]).numpy()[:, None]  # (B, 1, 3, 4)
    x = pts.numpy()
    # P @ [x; 1] summed left to right in float32, as torch's batched 3x4 @ 4x1 products do (bit-identical,
    # and ~300x faster than B x P tiny matmuls)
    suv = torch.as_tensor(((P[..., 0] * x[..., 0:1] + P[..., 1] * x[..., 1:2]) + P[..., 2] * x[..., 2:3]) + P[..., 3])
    z = suv[..., -1]
    suv[..., -1] = torch.max(torch.ones_like(z) * z_min, z)
    return suv[..., :2] / suv[..., [-1]]


def project_points_robust(points: np.ndarray, K: np.ndarray, T: np.ndarray, z_min: float = Z_MIN_MM) -> np.ndarray:
    """(B, P, 3) object points (mm), K (B, 3, 3), T_cam_obj (B, 4, 4) mm -> uv (B, P, 2) px with the
    camera depth clamped to >= z_min (mm); float32 like the original."""
    pts, Kt, Tt = _f32_m(points, K, T)
    return _project_f32(pts, Kt, Tt, z_min * 1e-3).numpy()


def boxes_from_uv(uv: np.ndarray) -> np.ndarray:
    return np.concatenate([uv.min(axis=1), uv.max(axis=1)], axis=-1)


def crop_boxes(K: np.ndarray, T: np.ndarray, points: np.ndarray, image_hw: tuple[int, int],
               lamb: float = LAMBDA) -> tuple[np.ndarray, np.ndarray]:
    """``deepim_crops_robust``'s boxes: (boxes_rend, boxes_crop), each (B, 4) px (float32 values).

    boxes_rend: min/max of the projected points (mm, (B, P, 3)). The crop is centred on the
    projected object origin, half sizes from the farthest box side, widened to the input image's
    aspect ratio r = max(H, W) / min(H, W), times lamb; not clipped."""
    pts, Kt, Tt = _f32_m(points, K, T)
    B = len(Tt)
    with torch.no_grad():
        uv = _project_f32(pts, Kt, Tt, Z_MIN_MM * 1e-3)
        rend = torch.cat([uv.min(dim=1).values, uv.max(dim=1).values], dim=-1)
        c = _project_f32(torch.zeros(B, 1, 3), Kt, Tt, Z_MIN_MM * 1e-3)[:, 0]
        xc, yc = c[:, 0], c[:, 1]
        H, W = image_hw
        r = max(H, W) / min(H, W)
        xdist = torch.max(torch.abs(rend[:, 0] - xc), torch.abs(rend[:, 2] - xc))
        ydist = torch.max(torch.abs(rend[:, 1] - yc), torch.abs(rend[:, 3] - yc))
        width = torch.max(xdist, ydist * r) * 2 * lamb
        height = torch.max(xdist / r, ydist) * 2 * lamb
        crop = torch.stack([xc - width / 2, yc - height / 2, xc + width / 2, yc + height / 2], dim=-1)
    return rend.numpy().astype(np.float64), crop.numpy().astype(np.float64)


def K_crop_resize(K: np.ndarray, boxes: np.ndarray, crop_hw: tuple[int, int] = CROP_HW) -> np.ndarray:
    """``get_K_crop_resize``: intrinsics (B, 3, 3) of the crops ``boxes`` (B, 4) resized to crop_hw
    (float32 like the original; the skew is kept, not scaled)."""
    b = torch.as_tensor(np.asarray(boxes, np.float64).reshape(-1, 4), dtype=torch.float32)
    K = torch.as_tensor(np.broadcast_to(np.asarray(K, np.float64), (len(b), 3, 3)).copy(), dtype=torch.float32)
    out_w, out_h = float(max(crop_hw)), float(min(crop_hw))
    cw, ch = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
    cj, ci = (b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2
    cx = K[:, 0, 2] + (cw - 1) / 2 - cj
    cy = K[:, 1, 2] + (ch - 1) / 2 - ci
    dx, dy = cx - (cw - 1) / 2, cy - (ch - 1) / 2
    sx, sy = out_w / cw, out_h / ch
    Kc = K.clone()
    Kc[:, 0, 0] = sx * K[:, 0, 0]
    Kc[:, 1, 1] = sy * K[:, 1, 1]
    Kc[:, 0, 2] = (out_w - 1) / 2 + sx * dx
    Kc[:, 1, 2] = (out_h - 1) / 2 + sy * dy
    return Kc.numpy().astype(np.float64)


def _roi_axis_weights(start: np.float32, end: np.float32, n_out: int, size: int,
                      ratio: int = SAMPLING_RATIO) -> np.ndarray:
    """(n_out, size) float64 weights of one axis of torchvision's roi_align (aligned=False): the
    mean over ``ratio`` bilinear samples per output bin, computed in float32 as torchvision does."""
    f32 = np.float32
    length = max(f32(end) - f32(start), f32(1.0))
    bin_ = f32(length / f32(n_out))
    p = np.arange(n_out, dtype=f32)[:, None]
    i = np.arange(ratio, dtype=f32)[None, :] + f32(0.5)
    s = (f32(start) + p * bin_) + (i * bin_) / f32(ratio)  # (n_out, ratio), float32
    s = s.astype(f32)
    valid = (s >= -1.0) & (s <= size)
    s = np.where(s <= 0, f32(0), s)
    low = s.astype(np.int64)
    top = low >= size - 1
    low = np.where(top, size - 1, low)
    high = np.where(top, size - 1, low + 1)
    s = np.where(top, low.astype(f32), s)
    frac = (s - low.astype(f32)).astype(f32)
    w_low = (f32(1) - frac) * valid
    w_high = frac * valid
    W = np.zeros((n_out, size), np.float64)
    rows = np.repeat(np.arange(n_out), ratio)
    np.add.at(W, (rows, low.reshape(-1)), w_low.reshape(-1).astype(np.float64))
    np.add.at(W, (rows, high.reshape(-1)), w_high.reshape(-1).astype(np.float64))
    return W / ratio


def roi_align(images: np.ndarray, boxes: np.ndarray, out_hw: tuple[int, int] = CROP_HW,
              image_index: np.ndarray | None = None) -> np.ndarray:
    """``torchvision.ops.roi_align(images, boxes, out_hw, spatial_scale=1, sampling_ratio=4,
    aligned=False)`` in numpy: (N, C, H, W) float images, boxes (B, 4) px, image_index (B,) (default
    arange) -> (B, C, h, w) float32. Bilinear roi_align is separable: each crop is Wy @ image @ Wx^T
    over the rows and columns the box touches."""
    images = np.asarray(images)
    boxes = np.asarray(boxes, np.float32).reshape(-1, 4)
    B = len(boxes)
    idx = np.arange(B) if image_index is None else np.asarray(image_index).reshape(-1)
    _, C, H, W = images.shape
    h, w = out_hw
    out = np.zeros((B, C, h, w), np.float32)
    for b in range(B):  # one pair of matrix products per crop
        Wy = _roi_axis_weights(boxes[b, 1], boxes[b, 3], h, H)
        Wx = _roi_axis_weights(boxes[b, 0], boxes[b, 2], w, W)
        ry = np.flatnonzero(Wy.any(0))
        rx = np.flatnonzero(Wx.any(0))
        if len(ry) == 0 or len(rx) == 0:
            continue
        y0, y1, x0, x1 = ry[0], ry[-1] + 1, rx[0], rx[-1] + 1
        img = np.asarray(images[idx[b], :, y0:y1, x0:x1], np.float32)
        rows = np.matmul(Wy[:, y0:y1].astype(np.float32), img)  # (C, h, x1 - x0)
        out[b] = np.matmul(rows, Wx[:, x0:x1].T.astype(np.float32))
    return out


def ortho6d_to_matrix(x: np.ndarray) -> np.ndarray:
    """``compute_rotation_matrix_from_ortho6d``: (B, 6) -> (B, 3, 3) with columns x, y, z:
    x = a/|a|, z = (x cross b)/|x cross b|, y = z cross x."""
    x = np.asarray(x, np.float64)
    a, b = x[:, :3], x[:, 3:6]
    ex = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-8)
    ez = np.cross(ex, b)
    ez = ez / np.maximum(np.linalg.norm(ez, axis=-1, keepdims=True), 1e-8)
    ey = np.cross(ez, ex)
    return np.stack([ex, ey, ez], axis=-1)


def update_poses(T: np.ndarray, K_crop: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """``update_pose`` (n_pose_dims 9): T_out (B, 4, 4) from T_in (B, 4, 4) mm, the crop intrinsics
    and the raw outputs (B, 9): z' = v_z z, (x', y') = (v_xy / f_crop + (x, y) / z) z', R' = dR R."""
    from .pose_update import apply_update_parts

    pose = np.asarray(pose, np.float64)
    with torch.no_grad():
        out = apply_update_parts(torch.as_tensor(np.asarray(T, np.float64)),
                                 torch.as_tensor(np.asarray(K_crop, np.float64)),
                                 torch.as_tensor(ortho6d_to_matrix(pose[:, :6])),
                                 torch.as_tensor(pose[:, 6:8]), torch.as_tensor(pose[:, 8]))
    return out.numpy()


def init_poses(K: np.ndarray, boxes: np.ndarray, points: np.ndarray | None, method: str) -> np.ndarray:
    """The coarse model's input poses (B, 4, 4) mm from 2D boxes (B, 4) (x1, y1, x2, y2 px), K (B, 3, 3).

    'z-up+auto-depth': R = ZUP_ROTATION, the depth that makes the points' (B, P, 3 mm) x/y extents
    match the box (``bb = x2 - x1 + 1``), the origin on the ray through the box centre.
    'v0': R = I, z = 1 m, same ray."""
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    B = len(b)
    K = np.broadcast_to(np.asarray(K, np.float64), (B, 3, 3))
    f = np.stack([K[:, 0, 0], K[:, 1, 1]], -1)
    c = np.stack([K[:, 0, 2], K[:, 1, 2]], -1)
    centre = np.stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2], -1)
    T = np.tile(np.eye(4), (B, 1, 1))
    if method == "v0":
        z = np.full(B, V0_DEPTH_MM)
    elif method == "z-up+auto-depth":
        T[:, :3, :3] = ZUP_ROTATION
        pc = np.asarray(points, np.float64) @ ZUP_ROTATION.T  # the extents do not depend on t
        dx = pc[..., 0].max(1) - pc[..., 0].min(1)
        dy = pc[..., 1].max(1) - pc[..., 1].min(1)
        z = (f[:, 0] * dx / (b[:, 2] - b[:, 0] + 1) + f[:, 1] * dy / (b[:, 3] - b[:, 1] + 1)) / 2
    else:
        raise CosyError(f"unknown CosyPose init_method {method!r} (expected one of {', '.join(INIT_METHODS)})")
    T[:, :2, 3] = (centre - c) * z[:, None] / f
    T[:, 2, 3] = z
    return T


# ------------------------------------------------------------------------------------------------
# the stage-1 loop
# ------------------------------------------------------------------------------------------------
@dataclass
class StepRecord:
    """Everything one iteration computed (for tests and debugging); poses mm."""

    T_input: np.ndarray
    boxes_rend: np.ndarray
    boxes_crop: np.ndarray
    K_crop: np.ndarray
    images_crop: np.ndarray
    renders: np.ndarray
    pose: np.ndarray
    T_output: np.ndarray


def light_dirs_cam(T: np.ndarray) -> np.ndarray:
    """(B, 3): the direction the original's light travels, in each camera frame."""
    d = -LIGHT_POS_OBJ / np.linalg.norm(LIGHT_POS_OBJ)
    return np.asarray(T, np.float64)[:, :3, :3] @ d


def render_crops(renderer, K_crop: np.ndarray, obj_ids, T: np.ndarray, ambient: float = RENDER_AMBIENT) -> np.ndarray:
    """(B, 3, 240, 320) float32 in [0, 1]: each object alone at its pose in its crop's camera,
    own colours/textures, black background, the original's object-fixed light; uint8 / 255 as
    the original's renderer output."""
    B = len(T)
    out = np.zeros((B, 3) + CROP_HW, np.float32)
    light = light_dirs_cam(T)
    h, w = CROP_HW
    for b in range(B):  # one call per crop: the light direction differs per crop
        r = renderer.render_crops(K_crop[b:b + 1], [int(obj_ids[b])], T[b:b + 1], (w, h), light_dir=light[b],
                                  ambient=ambient)
        out[b] = r.rgb[0].transpose(2, 0, 1).astype(np.float32) / 255.0
    return out


class CosyPoseRenderAndCompare:
    """One CosyPose network (coarse or refiner) run as the original ``PosePredictor`` does.

    net: a callable (B, 6, 240, 320) -> (B, 9) with ``kind`` and ``init_method``
    (:class:`OnnxCosyPoseNet`, :class:`TorchCosyPoseNet`); renderer: a cosy ``SceneRenderer`` with
    the objects' meshes (or ``render_fn(K_crop, obj_ids, T) -> (B, 3, 240, 320)``); points:
    :class:`MeshPoints` of the object set. Interface of :class:`~.render_compare.RenderAndCompare`
    (``step``, ``coarse``, ``iterate``) so ``cosy estimate`` uses either."""

    def __init__(self, net, renderer, points: MeshPoints, batch_size: int = 32, render_fn=None):
        self.net = net
        self.renderer = renderer
        self.points = points
        self.batch_size = int(batch_size)
        self.render_fn = render_fn or (lambda K_crop, ids, T: render_crops(self.renderer, K_crop, ids, T))

    @property
    def kind(self) -> str:
        return self.net.kind

    def forward(self, images: np.ndarray, K: np.ndarray, obj_ids, T: np.ndarray, image_index=None,
                renders: np.ndarray | None = None) -> StepRecord:
        """One iteration for B poses. images (N, 3, H, W) float32 in [0, 1] (RGB), image_index (B,)
        (default arange), K (B, 3, 3), T (B, 4, 4) mm; renders: inject (B, 3, 240, 320) instead of
        rendering."""
        T = np.asarray(T, np.float64)
        K = np.asarray(K, np.float64)
        pts = self.points.select(obj_ids)
        rend, crop = crop_boxes(K, T, pts, images.shape[-2:])
        K_crop = K_crop_resize(K, crop)
        crops = roi_align(images, crop, CROP_HW, image_index)
        if renders is None:
            renders = self.render_fn(K_crop, obj_ids, T)
        x = np.concatenate([crops, np.asarray(renders, np.float32)], axis=1)
        pose = np.asarray(self.net(x), np.float64)
        return StepRecord(T, rend, crop, K_crop, crops, renders, pose, update_poses(T, K_crop, pose))

    def step(self, rgb: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray, obj_ids) -> np.ndarray:
        """One iteration on N poses of one image rgb (H, W, 3) uint8 with K (3, 3): (N, 4, 4) mm."""
        T = np.asarray(T_cam_obj, np.float64).reshape(-1, 4, 4)
        ids = np.asarray(obj_ids).reshape(-1)
        out = T.copy()
        if len(T) == 0:
            return out
        img = (np.asarray(rgb, np.float32) / 255.0).transpose(2, 0, 1)[None]
        for s in range(0, len(T), self.batch_size):
            sl = slice(s, s + self.batch_size)
            n = len(T[sl])
            rec = self.forward(img, np.broadcast_to(K, (n, 3, 3)), ids[sl], T[sl], image_index=np.zeros(n, int))
            out[sl] = rec.T_output
        return out

    def initial_poses(self, K: np.ndarray, boxes: np.ndarray, obj_ids) -> np.ndarray:
        """The coarse input poses (N, 4, 4) mm from boxes (N, 4) with this run's init method."""
        b = np.asarray(boxes, np.float64).reshape(-1, 4)
        pts = self.points.select(np.asarray(obj_ids).reshape(-1)) if self.net.init_method != "v0" else None
        return init_poses(np.broadcast_to(K, (len(b), 3, 3)), b, pts, self.net.init_method)

    def coarse(self, rgb: np.ndarray, K: np.ndarray, boxes: np.ndarray, obj_ids) -> np.ndarray:
        """The coarse estimate: one iteration from the run's initial poses of the boxes."""
        return self.step(rgb, K, self.initial_poses(K, boxes, obj_ids), obj_ids)

    def iterate(self, rgb: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray, obj_ids, iterations: int) -> list:
        T = np.asarray(T_cam_obj, np.float64)
        history = []
        for _ in range(int(iterations)):
            T = self.step(rgb, K, T, obj_ids)
            history.append(T)
        return history
