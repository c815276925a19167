"""PyTorch modules to the evaluator's checkpoint format (`policy.json` + `policy.safetensors`), for every
architecture the leaderboard plays (README, "Policies and scoring"). Needs `torch` and `safetensors`
(`pip install "./client/python[torch]"`).

    export_policy(actor, task="OfflineCarRun-v0", architecture="mlp_actor", out_dir="bc-safe-20",
                  cost_threshold=20)                      # OSRL MLPActor (BC-All, BC-Safe)
    export_policy(model, ..., architecture="bcq_actor", cost_threshold=20)          # OSRL BCQL (actor + VAE)
    export_policy(actor, ..., architecture="squashed_gaussian_mlp", cost_threshold=20)  # BEAR-L, CPQ, COptiDICE
    export_policy(cdt, ..., architecture={"name": "cdt", "reward_scale": 0.1, ...},
                  targets=[{"cost_threshold": 10, "reward_return": 575, "cost_return": 10}, ...])

Sizes (hidden layers, latent size, CDT's dimensions) are read from the module; settings it cannot know (`max_action`,
`phi`, CDT's scales) come from the module's attributes where OSRL keeps them, else from `architecture` as a dict.

From arrays instead of modules (JAX/flax parameters, NumPy; no torch needed), any architecture, the multi-pass ones
included (`diffusion`, `latent_policy`), with the tensor names of the README's table:

    export_arrays({"actor.time.kernel": ..., "actor.cond.0.weight": ..., ...}, task="OfflineCarRun-v0",
                  architecture={"name": "diffusion", "time_dim": 64, ..., "sampler": {"kind": "ddpm", ...}},
                  out_dir="fisor")
    flax_dense(params["MLPResNet_0"]["Dense_0"], "actor.input")   # a flax Dense -> {name.weight, name.bias}
"""
import json
import os

from . import catalog

_ACTIVATIONS = {"ReLU": "relu", "Tanh": "tanh"}


def export_policy(module, *, task, architecture, out_dir, cost_threshold=None, targets=None, target_cost=False,
                  observation_normalization=None):
    """Writes `out_dir/policy.json` and `out_dir/policy.safetensors`; returns the policy.json document.

    Conditioning: `cost_threshold=K` (one checkpoint per threshold), `targets=[...]` (CDT's returns-to-go per
    threshold), `target_cost=True` (the threshold is one more input), or none of them (one policy for all)."""
    import torch
    from safetensors.torch import save_file

    info = catalog.task(task)
    settings = dict(architecture) if isinstance(architecture, dict) else {"name": architecture}
    name = settings.pop("name")
    writer = {"mlp_actor": _mlp_actor, "squashed_gaussian_mlp": _squashed, "gaussian_mlp": _gaussian,
              "bcq_actor": _bcq, "cdt": _cdt}.get(name)
    if writer is None:
        raise ValueError(f"unknown architecture {name!r}: one of mlp_actor, gaussian_mlp, squashed_gaussian_mlp, "
                         "bcq_actor, cdt")
    with torch.no_grad():
        tensors, arch = writer(module, settings, torch)
    config = _config(info, {"name": name, **arch, **settings}, cost_threshold, targets, target_cost,
                     observation_normalization)
    os.makedirs(out_dir, exist_ok=True)
    save_file(tensors, os.path.join(out_dir, "policy.safetensors"))
    return _write_config(out_dir, config)


def export_arrays(tensors, *, task, architecture, out_dir, cost_threshold=None, targets=None, target_cost=False,
                  observation_normalization=None):
    """Writes a checkpoint from named arrays (NumPy, or anything `numpy.asarray` takes: JAX arrays) and the
    architecture as `policy.json` declares it (a dict with its `name`); returns the policy.json document. The
    evaluator checks every name and shape against the declaration when the checkpoint is submitted."""
    import numpy as np

    info = catalog.task(task)
    arrays = {name: np.ascontiguousarray(np.asarray(value, dtype=np.float32)) for name, value in tensors.items()}
    config = _config(info, dict(architecture), cost_threshold, targets, target_cost, observation_normalization)
    os.makedirs(out_dir, exist_ok=True)
    _save_safetensors(arrays, os.path.join(out_dir, "policy.safetensors"))
    return _write_config(out_dir, config)


def flax_dense(params, name):
    """A flax `Dense` layer's parameters (`kernel` [in, out], `bias`) as a PyTorch-style linear layer `name`."""
    import numpy as np

    return {f"{name}.weight": np.asarray(params["kernel"]).T, f"{name}.bias": np.asarray(params["bias"])}


def _save_safetensors(arrays, path):
    """The safetensors layout: an 8-byte little-endian header length, a JSON header of names, dtypes, shapes and
    byte ranges, then the little-endian float32 data."""
    header, offset, chunks = {}, 0, []
    for name in sorted(arrays):
        data = arrays[name].astype("<f4").tobytes()
        header[name] = {"dtype": "F32", "shape": list(arrays[name].shape), "data_offsets": [offset, offset + len(data)]}
        offset += len(data)
        chunks.append(data)
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    with open(path + ".part", "wb") as f:
        f.write(len(text).to_bytes(8, "little") + text + b"".join(chunks))
    os.replace(path + ".part", path)


def _config(info, architecture, cost_threshold, targets, target_cost, observation_normalization):
    if sum(x is not None and x is not False for x in (cost_threshold, targets, target_cost or None)) > 1:
        raise ValueError("give one of cost_threshold, targets, target_cost")
    if cost_threshold is not None:
        conditioning = {"kind": "per_threshold", "cost_threshold": float(cost_threshold)}
    elif targets is not None:
        conditioning = {"kind": "returns_to_go", "targets": [dict(t) for t in targets]}
    elif target_cost:
        conditioning = {"kind": "target_cost"}
    else:
        conditioning = {"kind": "unconditioned"}
    config = {"format": "dsrl-policy/1", "task": info["id"], "obs_dim": info["obs_dim"], "act_dim": info["act_dim"],
              "architecture": architecture, "conditioning": conditioning}
    if observation_normalization is not None:
        mean, std = observation_normalization
        config["observation_normalization"] = {"mean": [float(x) for x in mean], "std": [float(x) for x in std]}
    return config


def _write_config(out_dir, config):
    with open(os.path.join(out_dir, "policy.json"), "w") as f:
        json.dump(config, f, indent=1)
    return config


def _linears(torch, modules):
    out = []
    for m in modules:
        out.extend(x for x in (m.modules() if hasattr(m, "modules") else [m]) if isinstance(x, torch.nn.Linear))
    return out


def _activation(torch, module, default):
    for m in module.modules():
        if type(m).__name__ in _ACTIVATIONS:
            return _ACTIVATIONS[type(m).__name__]
    return default


def _layers(prefix, linears):
    return {f"{prefix}.{i}.{k}": getattr(m, k).detach().float().contiguous()
            for i, m in enumerate(linears) for k in ("weight", "bias")}


def _hidden(linears):
    return [m.out_features for m in linears[:-1]]


def _max_action(module, settings):
    return float(settings.pop("max_action", getattr(module, "act_limit", getattr(module, "max_action", 1.0))))


def _mlp_actor(module, settings, torch):
    """OSRL `MLPActor`: its `net` (or `pi`) Sequential."""
    net = getattr(module, "net", None) or module.pi
    linears = _linears(torch, [net])
    return _layers("actor.net", linears), {"hidden_sizes": _hidden(linears),
                                           "activation": _activation(torch, net, "relu"),
                                           "max_action": _max_action(module, settings)}


def _squashed(module, settings, torch):
    """OSRL `SquashedGaussianMLPActor`: trunk `net`, heads `mu_layer` and `log_std_layer`."""
    trunk = _linears(torch, [module.net])
    tensors = {**_layers("actor.trunk", trunk), **_layers("actor.mu", [module.mu_layer])}
    if hasattr(module, "log_std_layer"):
        tensors.update(_layers("actor.log_std", [module.log_std_layer]))
    return tensors, {"hidden_sizes": [m.out_features for m in trunk], "activation": _activation(torch, module.net, "relu"),
                     "max_action": _max_action(module, settings)}


def _gaussian(module, settings, torch):
    """A Gaussian MLP actor with a `mu` network and a state-independent `log_std` parameter (DSRL's experts)."""
    linears = _linears(torch, [module.mu])
    tensors = _layers("actor.mu", linears)
    tensors["actor.log_std"] = module.log_std.detach().float().contiguous()
    return tensors, {"hidden_sizes": _hidden(linears), "activation": _activation(torch, module.mu, "tanh"),
                     "max_action": _max_action(module, settings)}


def _bcq(model, settings, torch):
    """OSRL BCQL: `model.actor` (MLPGaussianPerturbationActor, `pi`) and `model.vae` (decoder `d1..d3`)."""
    actor = _linears(torch, [model.actor.pi])
    decoder = [model.vae.d1, model.vae.d2, model.vae.d3]
    tensors = {**_layers("actor.pi", actor), **_layers("vae.decoder", decoder)}
    arch = {"hidden_sizes": _hidden(actor), "activation": _activation(torch, model.actor.pi, "tanh"),
            "decoder_hidden_sizes": [m.out_features for m in decoder[:-1]],
            "latent_dim": int(getattr(model.vae, "latent_dim", model.vae.d1.in_features - decoder[-1].out_features)),
            "phi": float(settings.pop("phi", getattr(model.actor, "phi", 0.05))),
            "max_action": _max_action(model.actor, settings)}
    return tensors, arch


def _cdt(cdt, settings, torch):
    """OSRL CDT: its state_dict under `cdt.` (the boolean causal-mask buffers are not weights)."""
    tensors = {f"cdt.{k}": v.detach().float().contiguous() for k, v in cdt.state_dict().items()
               if not k.endswith("causal_mask")}
    arch = {"embedding_dim": getattr(cdt, "embedding_dim", None),
            "num_layers": len(getattr(cdt, "blocks", [])) or None,
            "num_heads": None, "seq_len": getattr(cdt, "seq_len", None), "episode_len": getattr(cdt, "episode_len", None),
            "max_action": _max_action(cdt, settings), "reward_scale": 0.1, "cost_scale": 1.0,
            # OSRL keeps `cost_transform` as the function `50 - x`, or None.
            "cost_transform": getattr(cdt, "cost_transform", None) is not None}
    if hasattr(cdt, "blocks") and len(cdt.blocks) and hasattr(cdt.blocks[0], "attention"):
        arch["num_heads"] = int(cdt.blocks[0].attention.num_heads)
    for key in list(arch):
        if key in settings:
            arch[key] = settings.pop(key)
    missing = [k for k, v in arch.items() if v is None]
    if missing:
        raise ValueError(f"cdt: give {', '.join(missing)} in architecture (not found on the module)")
    return tensors, arch
