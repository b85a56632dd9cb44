"""Finding, downloading, converting and strictly loading the official weights.

Sources, in the order they are tried for a *name* (``vggt-1b``, ``vggt-1b-commercial``, a DINOv2 hub
name such as ``dinov2_vitb14``):

1. our cache: ``$VGGT_SLAM_PP_CACHE/weights/<name>.safetensors`` (default ``~/.cache/vggt-slam-pp``),
   written by ``vggt-slam-pp weights import`` / ``fetch``;
2. the Hugging Face cache (``facebook/VGGT-1B`` ``model.safetensors`` or ``model.pt``; DINOv2 in its
   Hugging Face format ``facebook/dinov2-base`` ...), then the torch-hub cache for DINOv2's
   ``*_pretrain.pth``;
3. a download (Hugging Face Hub via ``huggingface_hub``; DINOv2 release files from Meta's server)
   unless ``allow_download`` is false or ``HF_HUB_OFFLINE`` is set.

A *path* may be a file (``.pt``, ``.pth``, ``.bin``, ``.safetensors``) or a Hugging Face snapshot
folder. Key names are adapted where needed (``module.`` / ``model.`` prefixes, DINOv2's Hugging Face
naming with separate q/k/v) and then matched **strictly**: a wrong or partial checkpoint raises
:class:`WeightsError` naming the missing / unexpected / mis-shaped keys.
"""

from __future__ import annotations

import json
import logging
import os
import pickle
import re
import socket
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from vggt_slam_pp.errors import WeightsError
from vggt_slam_pp.models.dinov2 import HUB_NAMES, DinoVisionTransformer, build_dinov2
from vggt_slam_pp.models.vggt import VGGT, build_vggt

log = logging.getLogger(__name__)

VGGT_REPOS = {"vggt-1b": "facebook/VGGT-1B", "vggt-1b-commercial": "facebook/VGGT-1B-Commercial"}
VGGT_FILES = ("model.safetensors", "model.pt")
DINOV2_URL = "https://dl.fbaipublicfiles.com/dinov2"
_HF_SIZE = {"s": "small", "b": "base", "l": "large", "g": "giant"}
CHECKPOINT_SUFFIXES = (".safetensors", ".pt", ".pth", ".bin")
HOW_TO_PASS = ("pass a local checkpoint with --weights PATH (model.pt, .pth, .safetensors or a Hugging Face "
               "snapshot folder), or import one once with `vggt-slam-pp weights import PATH --name NAME`")


def known_names() -> tuple[str, ...]:
    return (*VGGT_REPOS, *HUB_NAMES)


def cache_dir() -> Path:
    """Our weights cache: ``$VGGT_SLAM_PP_CACHE/weights`` or ``~/.cache/vggt-slam-pp/weights``."""
    root = os.environ.get("VGGT_SLAM_PP_CACHE") or Path.home() / ".cache" / "vggt-slam-pp"
    return Path(root) / "weights"


def dinov2_release_file(name: str) -> str:
    """``dinov2_vitb14`` -> ``dinov2_vitb14/dinov2_vitb14_pretrain.pth`` (``_reg`` -> ``_reg4``)."""
    base = name.removesuffix("_reg")
    return f"{base}/{base}{'_reg4' if name.endswith('_reg') else ''}_pretrain.pth"


def dinov2_hf_repo(name: str) -> str:
    """``dinov2_vitb14`` -> ``facebook/dinov2-base``; ``_reg`` -> ``facebook/dinov2-with-registers-base``."""
    size = _HF_SIZE[name[len("dinov2_vit")]]
    return f"facebook/dinov2-{'with-registers-' if name.endswith('_reg') else ''}{size}"


# ------------------------------------------------------------------------------------------------
# Reading files
# ------------------------------------------------------------------------------------------------
def find_checkpoint_in_dir(folder: Path) -> list[Path]:
    """The checkpoint file(s) of a snapshot folder (sharded safetensors give several)."""
    index = folder / "model.safetensors.index.json"
    if index.is_file():
        shards = sorted(set(json.loads(index.read_text())["weight_map"].values()))
        return [folder / s for s in shards]
    for name in ("model.safetensors", "model.pt", "pytorch_model.bin", "model.pth"):
        if (folder / name).is_file():
            return [folder / name]
    found = sorted(p for p in folder.iterdir() if p.suffix in CHECKPOINT_SUFFIXES and p.is_file())
    if len(found) == 1:
        return found
    if not found:
        raise WeightsError(f"no checkpoint file ({', '.join(CHECKPOINT_SUFFIXES)}) in folder {folder}")
    raise WeightsError(f"several checkpoint files in {folder} ({', '.join(p.name for p in found)}); pass one")


def read_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """Tensors of a checkpoint file or snapshot folder, on CPU. Unwraps ``{"model": ...}``-style
    containers. Corrupt or truncated files raise :class:`WeightsError`."""
    path = Path(path).expanduser()
    if not path.exists():
        raise WeightsError(f"weights file not found: {path}")
    if path.is_dir():
        sd: dict[str, torch.Tensor] = {}
        for f in find_checkpoint_in_dir(path):
            sd.update(read_state_dict(f))
        return sd
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            obj = load_file(str(path), device="cpu")
        else:
            try:  # memory-mapped when the file is in torch's zip format (every recent torch.save)
                obj = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
            except RuntimeError as exc:
                if "mmap" not in str(exc):
                    raise
                obj = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, ValueError, EOFError, pickle.UnpicklingError, KeyError) as exc:
        raise WeightsError(f"cannot read weights {path} (truncated or not a checkpoint?): "
                           f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from exc
    except Exception as exc:  # noqa: BLE001 - safetensors raises its own SafetensorError
        raise WeightsError(f"cannot read weights {path} (truncated or corrupt?): {exc}") from exc
    while isinstance(obj, Mapping) and len(obj) <= 3:
        inner = next((obj[k] for k in ("model", "state_dict", "model_state_dict", "module")
                      if k in obj and isinstance(obj[k], Mapping)), None)
        if inner is None:
            break
        obj = inner
    if not isinstance(obj, Mapping) or not obj:
        raise WeightsError(f"{path} does not contain a state dict (got {type(obj).__name__})")
    bad = [k for k, v in obj.items() if not isinstance(v, torch.Tensor)]
    if bad:
        raise WeightsError(f"{path}: entries that are not tensors: {', '.join(map(str, bad[:5]))}")
    return dict(obj)


# ------------------------------------------------------------------------------------------------
# Key adaptation and strict loading
# ------------------------------------------------------------------------------------------------
_HF_DINO_RULES = [
    (r"^embeddings\.cls_token$", "cls_token"),
    (r"^embeddings\.mask_token$", "mask_token"),
    (r"^embeddings\.position_embeddings$", "pos_embed"),
    (r"^embeddings\.register_tokens$", "register_tokens"),
    (r"^embeddings\.patch_embeddings\.projection\.", "patch_embed.proj."),
    (r"^encoder\.layer\.(\d+)\.norm([12])\.", r"blocks.\1.norm\2."),
    (r"^encoder\.layer\.(\d+)\.attention\.output\.dense\.", r"blocks.\1.attn.proj."),
    (r"^encoder\.layer\.(\d+)\.layer_scale([12])\.lambda1$", r"blocks.\1.ls\2.gamma"),
    (r"^encoder\.layer\.(\d+)\.mlp\.fc([12])\.", r"blocks.\1.mlp.fc\2."),
    (r"^encoder\.layer\.(\d+)\.mlp\.weights_in\.", r"blocks.\1.mlp.w12."),
    (r"^encoder\.layer\.(\d+)\.mlp\.weights_out\.", r"blocks.\1.mlp.w3."),
    (r"^layernorm\.", "norm."),
]
_HF_QKV = re.compile(r"^encoder\.layer\.(\d+)\.attention\.attention\.(query|key|value)\.(weight|bias)$")


def dinov2_from_hf(sd: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """DINOv2 weights in Hugging Face ``transformers`` naming -> official naming (q, k, v -> ``qkv``)."""
    out: dict[str, torch.Tensor] = {}
    qkv: dict[tuple[str, str], dict[str, torch.Tensor]] = {}
    for key, value in sd.items():
        k = key.removeprefix("dinov2.")
        m = _HF_QKV.match(k)
        if m:
            qkv.setdefault((m.group(1), m.group(3)), {})[m.group(2)] = value
            continue
        for pattern, repl in _HF_DINO_RULES:
            if re.match(pattern, k):
                k = re.sub(pattern, repl, k)
                break
        out[k] = value
    for (layer, kind), parts in qkv.items():
        if set(parts) != {"query", "key", "value"}:
            raise WeightsError(f"layer {layer}: incomplete q/k/v {kind} in the Hugging Face checkpoint")
        out[f"blocks.{layer}.attn.qkv.{kind}"] = torch.cat([parts["query"], parts["key"], parts["value"]])
    return out


def _strip_prefixes(sd: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    out = dict(sd)
    for prefix in ("module.", "_orig_mod.", "model.", "backbone."):
        if out and all(k.startswith(prefix) for k in out):
            out = {k[len(prefix):]: v for k, v in out.items()}
    return out


def adapt_keys(sd: Mapping[str, torch.Tensor], expected: set[str],
               converters: tuple[Callable[[Mapping[str, torch.Tensor]], dict], ...] = ()) -> dict[str, torch.Tensor]:
    """The variant of ``sd`` (as is, prefixes stripped, converted) whose keys best match ``expected``."""
    candidates = [dict(sd), _strip_prefixes(sd)]
    for convert in converters:
        candidates.append(convert(candidates[-1]))
    return min(candidates, key=lambda c: len(expected.symmetric_difference(c)))


def _examples(keys: list[str], n: int = 5) -> str:
    head = ", ".join(keys[:n])
    return head + (f", ... ({len(keys) - n} more)" if len(keys) > n else "")


def load_checked(model: nn.Module, sd: Mapping[str, torch.Tensor], source: str) -> None:
    """Strictly load ``sd`` into ``model`` (possibly built on ``meta``), or raise naming the bad keys."""
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    missing = sorted(set(expected) - set(sd))
    unexpected = sorted(set(sd) - set(expected))
    wrong = sorted(f"{k} {tuple(sd[k].shape)} != {expected[k]}" for k in set(expected) & set(sd)
                   if tuple(sd[k].shape) != expected[k])
    if missing or unexpected or wrong:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing keys ({_examples(missing)})")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected keys ({_examples(unexpected)})")
        if wrong:
            parts.append(f"{len(wrong)} keys with the wrong shape ({_examples(wrong, 3)})")
        raise WeightsError(f"{source} does not match {type(model).__name__}: " + "; ".join(parts))
    bad = [k for k, v in sd.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise WeightsError(f"{source} contains non-finite values in {_examples(sorted(bad))}")
    meta = any(p.is_meta for p in model.parameters())
    model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in sd.items()},
                          strict=True, assign=meta)


# ------------------------------------------------------------------------------------------------
# Resolving names to files
# ------------------------------------------------------------------------------------------------
def _offline() -> bool:
    return os.environ.get("HF_HUB_OFFLINE", "0").lower() in ("1", "true", "yes")


def _reachable(host: str, timeout: float = 3.0) -> bool:
    """Cheap connectivity probe so that an offline machine fails fast instead of retrying downloads."""
    try:
        socket.create_connection((host, 443), timeout=timeout).close()
        return True
    except OSError:
        log.info("%s is not reachable; not downloading", host)
        return False


def _hf_file(repo: str, filename: str, download: bool) -> Path | None:
    try:
        from huggingface_hub import hf_hub_download
    except ImportError:  # pragma: no cover - a declared dependency
        return None
    try:
        return Path(hf_hub_download(repo, filename, local_files_only=True))
    except Exception:  # noqa: BLE001 - not cached: any of several hub exceptions
        pass
    if not download or not _reachable("huggingface.co"):
        return None
    try:
        log.info("downloading %s/%s from the Hugging Face Hub", repo, filename)
        return Path(hf_hub_download(repo, filename))
    except Exception as exc:  # noqa: BLE001 - network/auth/not-found: reported by the caller
        log.info("download of %s/%s failed: %s", repo, filename, str(exc).splitlines()[0] if str(exc) else exc)
        return None


def _torch_hub_file(relative: str, download: bool) -> Path | None:
    target = Path(torch.hub.get_dir()) / "checkpoints" / Path(relative).name
    if target.is_file():
        return target
    if not download or not _reachable("dl.fbaipublicfiles.com"):
        return None
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        log.info("downloading %s/%s", DINOV2_URL, relative)
        torch.hub.download_url_to_file(f"{DINOV2_URL}/{relative}", str(target), progress=False)
        return target
    except (OSError, ValueError) as exc:
        log.info("download of %s failed: %s", relative, exc)
        return None


def resolve_weights(name_or_path: str | Path, allow_download: bool = True) -> Path:
    """A checkpoint path for a file/folder path or a known name (see the module docstring)."""
    path = Path(str(name_or_path)).expanduser()
    if path.exists():
        return path
    name = str(name_or_path)
    if name not in known_names():
        if any(str(name_or_path).endswith(s) for s in CHECKPOINT_SUFFIXES) or os.sep in name:
            raise WeightsError(f"weights file not found: {path}")
        raise WeightsError(f"unknown weights {name!r}: not a file and not one of {', '.join(known_names())}")
    ours = cache_dir() / f"{name}.safetensors"
    if ours.is_file():
        return ours
    download = allow_download and not _offline()
    if name in VGGT_REPOS:
        for local_only in (True, False):
            for filename in VGGT_FILES:
                found = _hf_file(VGGT_REPOS[name], filename, download=download and not local_only)
                if found:
                    return found
        where = f"Hugging Face repository {VGGT_REPOS[name]}"
    else:
        found = (_hf_file(dinov2_hf_repo(name), "model.safetensors", download=False)
                 or _torch_hub_file(dinov2_release_file(name), download=False)
                 or _torch_hub_file(dinov2_release_file(name), download=download)
                 or _hf_file(dinov2_hf_repo(name), "model.safetensors", download=download))
        if found:
            return found
        where = f"{DINOV2_URL}/{dinov2_release_file(name)} or {dinov2_hf_repo(name)}"
    state = "downloads are disabled" if not download else "the download failed (offline?)"
    raise WeightsError(f"weights {name!r} are not cached and {state} ({where}); {HOW_TO_PASS}")


def _model_for(name: str, device: str | torch.device | None) -> nn.Module:
    if name in VGGT_REPOS:
        return build_vggt({}, device=device)
    return build_dinov2(name, device=device)


def _converters(model: nn.Module):
    return (dinov2_from_hf,) if isinstance(model, DinoVisionTransformer) else ()


def _finish(model: nn.Module, device: str | torch.device) -> nn.Module:
    if isinstance(model, VGGT):
        model.aggregator.reset_buffers()
    return model.to(device).eval()


def load_vggt(weights: str | Path = "vggt-1b", config: Mapping | None = None,
              device: str | torch.device = "cpu", allow_download: bool = True) -> VGGT:
    """VGGT with weights from a name (``vggt-1b``, ``vggt-1b-commercial``) or a path. ``config`` is the
    nested configuration of :func:`build_vggt` (default VGGT-1B). Built on ``meta`` and filled from the
    checkpoint, so the weights are held in memory once."""
    path = resolve_weights(weights, allow_download)
    model = build_vggt(config or {}, device="meta")
    load_checked(model, adapt_keys(read_state_dict(path), set(model.state_dict())), str(path))
    return _finish(model, device)


def load_dinov2(spec: str | Mapping = "dinov2_vitb14", weights: str | Path | None = None,
                device: str | torch.device = "cpu", allow_download: bool = True) -> DinoVisionTransformer:
    """A DINOv2 ViT (hub name or config dictionary) with weights from ``weights`` (path or name) or,
    by default, the hub name's official checkpoint. Hugging Face ``transformers`` naming is converted."""
    if weights is None:
        if not isinstance(spec, str):
            raise WeightsError("a DINOv2 built from a config dictionary needs an explicit weights path")
        weights = spec
    path = resolve_weights(weights, allow_download)
    model = build_dinov2(spec, device="meta")
    load_checked(model, adapt_keys(read_state_dict(path), set(model.state_dict()), (dinov2_from_hf,)), str(path))
    return _finish(model, device)


# ------------------------------------------------------------------------------------------------
# Cache management (the `weights` command)
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CachedWeights:
    name: str
    path: Path
    size_bytes: int
    where: str  # "ours", "huggingface", "torch-hub"


def import_weights(path: str | Path, name: str) -> Path:
    """Validate a checkpoint for ``name`` (strict keys) and store it as safetensors in our cache."""
    if name not in known_names():
        raise WeightsError(f"unknown model name {name!r}; expected one of {', '.join(known_names())}")
    source = resolve_weights(path, allow_download=False)
    model = _model_for(name, "meta")
    sd = adapt_keys(read_state_dict(source), set(model.state_dict()), _converters(model))
    load_checked(model, sd, str(source))
    from safetensors.torch import save_file

    target = cache_dir() / f"{name}.safetensors"
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_suffix(".safetensors.tmp")
    save_file({k: v.contiguous() for k, v in sd.items()}, str(tmp), metadata={"source": str(source)})
    tmp.replace(target)
    return target


def fetch_weights(name: str) -> Path:
    """Make ``name`` available locally (download if needed) and return where it is."""
    if name not in known_names():
        raise WeightsError(f"unknown model name {name!r}; expected one of {', '.join(known_names())}")
    return resolve_weights(name, allow_download=True)


def cached_weights() -> list[CachedWeights]:
    """Every known checkpoint present on this machine (our cache, Hugging Face cache, torch hub)."""
    out: list[CachedWeights] = []
    for name in known_names():
        ours = cache_dir() / f"{name}.safetensors"
        if ours.is_file():
            out.append(CachedWeights(name, ours, ours.stat().st_size, "ours"))
        if name in VGGT_REPOS:
            hf = [_hf_file(VGGT_REPOS[name], f, download=False) for f in VGGT_FILES]
        else:
            hf = [_hf_file(dinov2_hf_repo(name), "model.safetensors", download=False)]
            th = _torch_hub_file(dinov2_release_file(name), download=False)
            if th:
                out.append(CachedWeights(name, th, th.stat().st_size, "torch-hub"))
        out.extend(CachedWeights(name, p, p.stat().st_size, "huggingface") for p in hf if p)
    return out
