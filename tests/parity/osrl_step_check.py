"""One training step of dsrl-train's candle learners (BCQ-Lag, BEAR-Lag, CPQ, COptiDICE, CDT) held to OSRL's own
PyTorch code (osrl-lib 0.1.0, installed, not copied): the same initial weights, the same batch and the same random
numbers, then every loss, every gradient each optimizer steps with, and every weight after the step (targets' soft
updates included) compared, part by part.

The random numbers: dsrl-train draws from its SplitMix64 stream (dsrl_policy::noise), which this script reproduces
bit for bit in Python (Stream below). OSRL draws from torch.randn / torch.randn_like and torch.distributions.Normal;
while OSRL runs, those return the draws dsrl-train makes, in the order each OSRL call consumes them (PLANS below:
where OSRL draws again for something dsrl-train draws once, e.g. BCQ-L's second decode of the same next states, the
same draws are replayed).
The initial weights are OSRL's (torch.manual_seed), loaded into dsrl-train by module and parameter order (CDT: by
parameter name, as its exports) through `dsrl-train parity` (hidden). CDT runs without dropout, so its step draws
nothing; its gradients are taken before OSRL clips them (dsrl-train's optimizer records them before clipping too).

Usage: .venv-bench/bin/python tests/parity/osrl_step_check.py DSRL_TRAIN [--table FILE] [ALGO ...]
(see osrl_step_check.sh). Prints one JSON line per algorithm with the largest differences (and with --table writes
them as a Markdown table); exits non-zero when one is over its tolerance.
"""
import contextlib
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "bench"))
from offline_step_torch import ALGOS, COMMON, SCALES, stand_in_loggers  # noqa: E402

OBS, ACT, BATCH, HIDDEN, VAE_HIDDEN, SEED = 6, 2, 64, [64, 64], 48, 11
MASK = (1 << 64) - 1
# Relative tolerances (largest difference over the largest magnitude) of losses and gradients, and of the change
# each weight made. The weights' is looser: Adam's first step is lr·g/(|g| + 1e-8), which turns a gradient's
# rounding into a large relative change wherever |g| is near 1e-8.
TOLERANCE = {"loss": 1e-4, "grad": 1e-4, "param": 1e-3}
ULPS = 4
SLACK = 8


class Stream:
    """dsrl_policy::noise::Noise: SplitMix64, uniform in (0, 1), Box-Muller keeping the cosine branch."""

    def __init__(self, seed):
        self.state = seed & MASK

    def next_u64(self):
        self.state = (self.state + 0x9E3779B97F4A7C15) & MASK
        z = self.state
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK
        return z ^ (z >> 31)

    def uniform(self):
        return ((self.next_u64() >> 11) + 0.5) / float(1 << 53)

    def normal(self):
        u1, u2 = self.uniform(), self.uniform()
        return math.sqrt(-2.0 * math.log(u1)) * math.cos(math.tau * u2)

    def normals(self, *shape):
        return torch.tensor([self.normal() for _ in range(int(np.prod(shape)))], dtype=torch.float32).reshape(shape)


def plan_bcql(stream, model):
    """dsrl-train: ε for the VAE [b, latent]; latents for the targets [b·n, latent], shared by both critics;
    latents for the actor [b, latent]. OSRL: randn_like in VAE.forward, then randn in each decode."""
    latent, n = model.latent_dim, model.sample_action_num
    eps = stream.normals(BATCH, latent)
    targets = stream.normals(BATCH * n, latent)
    actor = stream.normals(BATCH, latent)
    return [eps, targets, targets, actor]


def plan_coptidice(stream, model):
    """dsrl-train: noise on the observations [b, obs] and on the actions [b, act] of the policy extraction.
    OSRL: randn_like(observations), randn_like(actions), then its actor samples an action it does not use (None)."""
    return [stream.normals(BATCH, OBS), stream.normals(BATCH, ACT), None]


def plan_cpq(stream, model):
    """dsrl-train: ε for the VAE; an action for the reward critic's next states, another for the cost critic's;
    the out-of-distribution draws [n·b, act] (sample-major, as `pi_dist.sample([n])`); an action for the actor.
    OSRL draws two things more that it never uses (None: zeros): the action its cost-critic step samples beside the
    distribution it wants, and the VAE's latent sample for the drawn actions (only the encoder's mean and spread
    count)."""
    b, n, act, latent = BATCH, model.sample_action_num, ACT, model.latent_dim
    eps = stream.normals(b, latent)
    next_reward = stream.normals(b, act)
    next_cost = stream.normals(b, act)
    ood = stream.normals(n * b, act).reshape(n, b, act)
    actor = stream.normals(b, act)
    return [eps, next_reward, next_cost, None, ood, torch.zeros(n * b, latent), actor]


def plan_bearl(stream, model):
    """dsrl-train: ε for the VAE; the target actor's actions for the reward critic's repeated next states, and new
    ones for the cost critic's (OSRL draws in each too); the latents of the VAE's decodes [b·m, latent] (OSRL:
    [b, m, latent]); the actor's draws for the MMD [b·m, act]."""
    b, n, m = BATCH, model.sample_action_num, model.num_samples_mmd_match
    eps = stream.normals(b, model.vae.latent_dim)
    reward_next = stream.normals(b * n, ACT)
    cost_next = stream.normals(b * n, ACT)
    latents = stream.normals(b * m, model.vae.latent_dim).reshape(b, m, model.vae.latent_dim)
    actor = stream.normals(b * m, ACT)
    return [eps, reward_next, cost_next, latents, actor]


PLANS = {"bcql": plan_bcql, "bearl": plan_bearl, "coptidice": plan_coptidice, "cpq": plan_cpq}
# What to record from OSRL's methods, under dsrl-train's figure names: None is the loss a method returns as
# (loss, stats); a string is a key of the stats it returns.
CAPTURE = {
    "bcql": {"vae_loss": {"vae": None}, "critic_loss": {"critic": None}, "cost_critic_loss": {"cost_critic": None},
             "actor_loss": {"actor": None, "lagrangian": "loss/lagrangian"}},
    "bearl": {"vae_loss": {"vae": None}, "critic_loss": {"critic": None}, "cost_critic_loss": {"cost_critic": None},
              "actor_loss": {"actor": None, "mmd": "loss/mmd_loss", "alpha": "loss/alpha_value",
                             "lagrangian": "loss/lagrangian"}},
    "cpq": {"vae_loss": {"vae": None}, "critic_loss": {"critic": None},
            "cost_critic_loss": {"cost_critic": None, "alpha": "loss/alpha_value"}, "actor_loss": {"actor": None}},
    "coptidice": {"update": {"nu": "loss/nu_loss", "chi": "loss/chi_loss", "actor": "loss/actor_loss",
                             "td_error": "loss/td_error", "d_kl": "loss/D_kl", "d_f": "loss/Df", "tau": "loss/tau",
                             "lagrangian": "loss/lmbda"}},
}
# OSRL's attributes, in dsrl-train's module order (`dsrl-train parity` loads them by these names).
MODULES = {"bcql": ["actor", "critic", "cost_critic", "vae", "actor_old", "critic_old", "cost_critic_old"],
           "bearl": ["actor", "critic", "cost_critic", "vae", "actor_old", "critic_old", "cost_critic_old"],
           "cpq": ["actor", "critic", "cost_critic", "vae", "critic_old", "cost_critic_old"],
           "coptidice": ["actor", "nu_network", "chi_network", "tau", "lmbda"]}
OPTIMIZERS = {"bcql": ["actor_optim", "critic_optim", "cost_critic_optim", "vae_optim"],
              "bearl": ["actor_optim", "critic_optim", "cost_critic_optim", "vae_optim"],
              "cpq": ["actor_optim", "critic_optim", "cost_critic_optim", "vae_optim"],
              "coptidice": ["actor_optim", "nu_optim", "chi_optim", "tau_optim", "lmbda_optim"]}


def parameters(model, name):
    """An OSRL attribute's parameters: a module's, or the attribute itself (COptiDICE's τ and λ tensors)."""
    attr = getattr(model, name)
    return [attr] if isinstance(attr, torch.Tensor) else list(attr.parameters())


@contextlib.contextmanager
def injected(draws):
    """OSRL's standard-normal draws answer `draws` in order (shapes checked; None: zeros of the asked shape), and
    all must be used: torch.randn and torch.randn_like, the draws behind torch.distributions.Normal's rsample
    (`_standard_normal`) and sample (`torch.normal(loc, scale)`, as loc + z·scale)."""
    import torch.distributions.normal as normal_module
    queue = list(draws)
    saved = (torch.randn, torch.randn_like, torch.normal, normal_module._standard_normal)

    def take(shape):
        shape = tuple(shape)
        if not queue:
            raise AssertionError(f"OSRL drew {shape} more than planned")
        draw = queue.pop(0)
        if draw is None:
            return torch.zeros(shape)
        if tuple(draw.shape) != shape:
            raise AssertionError(f"OSRL drew {shape} where the plan has {tuple(draw.shape)}")
        return draw.clone()

    def normal(mean, std, *args, **kw):
        return mean + take(mean.shape) * std

    torch.randn = lambda *size, **kw: take(size[0] if len(size) == 1 and isinstance(size[0], (tuple, list, torch.Size))
                                           else size)
    torch.randn_like = lambda t, **kw: take(t.shape)
    torch.normal = normal
    normal_module._standard_normal = lambda shape, dtype=None, device=None: take(shape)
    try:
        yield
    finally:
        torch.randn, torch.randn_like, torch.normal, normal_module._standard_normal = saved
    if queue:
        raise AssertionError(f"{len(queue)} planned draws were not used by OSRL")


def batch(rng):
    u = lambda *s: torch.from_numpy(rng.uniform(-1, 1, size=s).astype(np.float32))  # noqa: E731
    done = torch.from_numpy((rng.uniform(size=BATCH) < 0.1).astype(np.float32))
    return {
        "observations": u(BATCH, OBS), "next_observations": u(BATCH, OBS), "actions": u(BATCH, ACT) * 0.9,
        "rewards": torch.from_numpy(rng.uniform(0, 2, size=BATCH).astype(np.float32)) * SCALES["reward_scale"],
        "costs": torch.from_numpy((rng.uniform(size=BATCH) < 0.3).astype(np.float32)) * SCALES["cost_scale"],
        "done": done, "is_init": torch.cat([torch.ones(1), done[:-1]]),
    }


def relative(a, b):
    a, b = a.double(), b.double()
    scale = max(a.abs().max().item(), b.abs().max().item(), 1e-12)
    return (a - b).abs().max().item() / scale


def osrl_step(algo, algorithms, DummyLogger, data, dtype):
    """OSRL's model (seeded) and one trainer step in `dtype`: (initial weights, figures, gradients, weights)."""
    torch.manual_seed(SEED)
    name, model_kw, trainer_kw = ALGOS[algo]
    model_kw = dict(model_kw)
    if "vae_hidden_sizes" in model_kw:
        model_kw["vae_hidden_sizes"] = VAE_HIDDEN
    if algo == "coptidice":
        # What dsrl-train computes from its data (here the batch's rows), as OSRL's TransitionDataset does.
        model_kw.update(init_state_propotion=data["is_init"].mean().item(),
                        observations_std=data["observations"].numpy().std(0),
                        actions_std=data["actions"].numpy().std(0))
    model = getattr(algorithms, name)(state_dim=OBS, action_dim=ACT, max_action=1.0, a_hidden_sizes=HIDDEN,
                                      c_hidden_sizes=HIDDEN, device="cpu", **COMMON, **model_kw)
    init = {f"{m}/{i}": p.detach().clone().contiguous()
            for m in MODULES[algo] for i, p in enumerate(parameters(model, m))}
    model.to(dtype)
    for m in MODULES[algo]:
        attr = getattr(model, m)
        if isinstance(attr, torch.Tensor):  # COptiDICE's τ and λ: leaf tensors, not module parameters
            setattr(model, m, attr.detach().to(dtype).requires_grad_(True))
    if algo == "coptidice":
        model.observations_std = model.observations_std.to(dtype)
        model.actions_std = model.actions_std.to(dtype)
    trainer = getattr(algorithms, name + "Trainer")(model, None, logger=DummyLogger(), device="cpu", **SCALES,
                                                    **trainer_kw)
    figures, grads = {}, {}
    for method, wanted in CAPTURE[algo].items():
        original = getattr(model, method)

        def record(*args, _wanted=wanted, _original=original, **kw):
            result = _original(*args, **kw)
            loss, stats = result if isinstance(result, tuple) else (None, result)
            for figure, key in _wanted.items():
                figures[figure] = loss.item() if key is None else float(stats[key])
            return result
        setattr(model, method, record)
    for opt_name in OPTIMIZERS[algo]:
        optimizer = getattr(model, opt_name)
        original_step = optimizer.step

        def step(*args, _name=opt_name, _optimizer=optimizer, _step=original_step, **kw):
            grads[_name] = [p.grad.detach().clone() if p.grad is not None else None
                            for g in _optimizer.param_groups for p in g["params"]]
            return _step(*args, **kw)
        optimizer.step = step
    keys = ["observations", "next_observations", "actions", "rewards", "costs", "done"]
    batch_in = {k: v.to(dtype) for k, v in data.items()}
    plan = [None if d is None else d.to(dtype) for d in PLANS[algo](Stream(SEED), model)]
    with injected(plan):
        if algo == "coptidice":
            trainer.train_one_step([batch_in[k] for k in keys + ["is_init"]])
        else:
            trainer.train_one_step(*[batch_in[k] for k in keys])
    params = {f"{m}/{i}": p.detach().clone() for m in MODULES[algo] for i, p in enumerate(parameters(model, m))}
    return init, figures, grads, params


def check(algo, dsrl_train, algorithms, DummyLogger):
    data = batch(np.random.default_rng(SEED))
    init, losses, grads, params = osrl_step(algo, algorithms, DummyLogger, data, torch.float32)
    _, losses64, grads64, params64 = osrl_step(algo, algorithms, DummyLogger, data, torch.float64)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        save_file(init, tmp / "init.safetensors")
        save_file({k: v.contiguous() for k, v in data.items()}, tmp / "batch.safetensors")
        (tmp / "parity.json").write_text(json.dumps({
            "algorithm": algo, "obs_dim": OBS, "act_dim": ACT, "hidden_sizes": HIDDEN, "vae_hidden": VAE_HIDDEN,
            "cost_threshold": COMMON["cost_limit"], "episode_len": COMMON["episode_len"], "noise_seed": SEED}))
        subprocess.run([dsrl_train, "parity", str(tmp)], check=True)
        ours = load_file(tmp / "candle.safetensors")
    flat = lambda gs: {f"grad/{o}/{i}": g for o, lst in gs.items() for i, g in enumerate(lst)}  # noqa: E731
    return compare(algo, losses, losses64, flat(grads), flat(grads64), params, params64, init, ours)


def compare(algo, losses, losses64, grads, grads64, params, params64, init, ours):
    """candle against OSRL in float32, and both against OSRL in float64 (the float32 rounding both have to live
    with): a difference passes when it is within the tolerance, or when candle is no further from the float64
    result than SLACK times PyTorch's own float32 result is. Prints and returns the result (`ok`: all pass)."""
    # Per kind: the largest difference, where, and (when over its tolerance) how far candle and PyTorch's float32
    # each are from float64.
    worst = {"loss": (0.0, "", None), "grad": (0.0, "", None), "param": (0.0, "", None)}
    failures = []

    def judge(kind, key, theirs, mine, exact, before=None):
        if before is not None:  # weights: measured on the change the step made
            theirs, mine, exact = theirs - before, mine - before, exact - before
        d = relative(theirs, mine)
        if before is not None:
            # A target network moves by τ of an update, where the weight's own float32 rounding is the floor.
            ulps = (theirs - mine).abs().max().item() / ((theirs + before).abs().max().item() * 2.0 ** -23 + 1e-30)
            if ulps <= ULPS:
                d = 0.0
        float64 = None
        if d > TOLERANCE[kind]:
            candle_error, torch_error = relative(exact, mine), relative(exact, theirs)
            float64 = {"candle": candle_error, "pytorch": torch_error}
            if candle_error > SLACK * torch_error:
                failures.append(f"{key}: {d:.2e} from OSRL's float32; from float64 candle {candle_error:.2e}, "
                                f"PyTorch float32 {torch_error:.2e}")
        if d > worst[kind][0]:
            worst[kind] = (d, key, float64)

    for figure, value in losses.items():
        judge("loss", f"loss/{figure}", torch.tensor(value, dtype=torch.float64),
              ours[f"loss/{figure}"].reshape(()).double(), torch.tensor(losses64[figure], dtype=torch.float64))
    for key, g in grads.items():
        if g is None or key not in ours:
            # A parameter the loss does not reach: no gradient on one side, zeros (or none) on the other.
            other = ours.get(key) if g is None else g
            if other is not None and other.abs().max().item() > 0:
                failures.append(f"{key}: a gradient on one side only")
            continue
        judge("grad", key, g.double(), ours[key].double(), grads64[key].double())
    for key in ours:
        if key.startswith("grad/") and key not in grads:
            failures.append(f"{key}: candle has a gradient OSRL does not")
    for key, p in params.items():
        judge("param", f"param/{key}", p.double(), ours[f"param/{key}"].double(), params64[key].double(),
              before=init[key].double())
    result = {"algorithm": algo, "ok": not failures,
              "largest_relative_difference": {k: v[0] for k, v in worst.items()},
              "where": {k: v[1] for k, v in worst.items()},
              "float64_error": {k: v[2] for k, v in worst.items() if v[2] is not None}, "failures": failures[:10],
              "losses": losses, "tolerance": TOLERANCE, "slack": SLACK}
    print(json.dumps(result))
    return result


# CDT at small sizes: embedding, layers, heads, window; episodes of CDT_EPISODE steps; batch CDT_BATCH windows.
CDT_SIZES, CDT_EPISODE, CDT_BATCH = (32, 2, 4, 5), 50, 16


class Recorder:
    """A logger that keeps what OSRL's CDTTrainer stores (its figures)."""

    def __init__(self):
        self.figures = {}

    def store(self, tab=None, **figures):
        self.figures.update({k: float(v) for k, v in figures.items()})


def cdt_windows(rng):
    """Windows as OSRL's SequenceDataset gives them: padding at the end of some (mask 0, zero inputs)."""
    b, k = CDT_BATCH, CDT_SIZES[3]
    lengths = rng.integers(2, k + 1, size=b)
    mask = (np.arange(k)[None, :] < lengths[:, None]).astype(np.float32)
    f = lambda *s: rng.uniform(-1, 1, size=s).astype(np.float32)  # noqa: E731
    start = rng.integers(0, CDT_EPISODE - k, size=b)
    return {
        "states": torch.from_numpy(f(b, k, OBS) * mask[..., None]),
        "actions": torch.from_numpy(0.9 * f(b, k, ACT) * mask[..., None]),
        # Returns-to-go as the trainer receives them: scaled (reward 0.1, cost 1) by OSRL's dataset.
        "returns": torch.from_numpy((rng.uniform(0, 3, size=(b, k)) * mask).astype(np.float32)),
        "costs_return": torch.from_numpy((rng.integers(0, 40, size=(b, k)) * mask).astype(np.float32)),
        "time_steps": torch.from_numpy(start[:, None] + np.arange(k)[None, :]).long(),
        "mask": torch.from_numpy(mask),
        "episode_cost": torch.zeros(b),
        "costs": torch.from_numpy(((rng.uniform(size=(b, k)) < 0.3) * mask).astype(np.float32)),
    }


def cdt_step(algorithms, data, dtype):
    """OSRL's CDT (seeded, no dropout) and one CDTTrainer step: (initial weights, figures, gradients before
    clipping, weights), by parameter name (`cdt.<name>` as its exports, and `log_temperature`)."""
    torch.manual_seed(SEED)
    embedding, layers, heads, k = CDT_SIZES
    model = algorithms.CDT(state_dim=OBS, action_dim=ACT, max_action=1.0, seq_len=k, episode_len=CDT_EPISODE,
                           embedding_dim=embedding, num_layers=layers, num_heads=heads, attention_dropout=0.0,
                           residual_dropout=0.0, embedding_dropout=0.0, time_emb=True, use_rew=True, use_cost=True,
                           cost_transform=True, stochastic=True, init_temperature=0.1, target_entropy=-ACT)
    named = dict(model.named_parameters())
    init = {f"cdt.{n}": p.detach().clone().contiguous() for n, p in named.items()}
    init["log_temperature"] = model.log_temperature.detach().to(torch.float32).reshape(1).clone()
    model.to(dtype)
    model.log_temperature = model.log_temperature.detach().to(dtype).requires_grad_(True)
    recorder = Recorder()
    trainer = algorithms.CDTTrainer(model, None, logger=recorder, learning_rate=1e-4, weight_decay=1e-4,
                                    betas=(0.9, 0.999), clip_grad=0.25, lr_warmup_steps=500, reward_scale=0.1,
                                    cost_scale=1.0, loss_cost_weight=0.02, loss_state_weight=0.0, device="cpu")
    grads = {}
    clip = torch.nn.utils.clip_grad_norm_

    def snapshot_then_clip(parameters, *args, **kw):
        parameters = list(parameters)
        for n, p in model.named_parameters():
            if p.grad is not None:
                grads[f"grad/optim/cdt.{n}"] = p.grad.detach().clone()
        return clip(parameters, *args, **kw)
    torch.nn.utils.clip_grad_norm_ = snapshot_then_clip
    temperature_step = trainer.log_temperature_optimizer.step

    def record_temperature(*args, **kw):
        grads["grad/log_temperature_optimizer/log_temperature"] = model.log_temperature.grad.detach().reshape(1)
        return temperature_step(*args, **kw)
    trainer.log_temperature_optimizer.step = record_temperature
    keys = ["states", "actions", "returns", "costs_return", "time_steps", "mask", "episode_cost", "costs"]
    try:
        trainer.train_one_step(*[data[k].to(dtype) if data[k].is_floating_point() else data[k] for k in keys])
    finally:
        torch.nn.utils.clip_grad_norm_ = clip
    params = {f"cdt.{n}": p.detach().clone() for n, p in model.named_parameters()}
    params["log_temperature"] = model.log_temperature.detach().reshape(1).clone()
    figures = {"loss": recorder.figures["all_loss"], "action": recorder.figures["act_loss"],
               "cost": recorder.figures["cost_loss"], "entropy": recorder.figures["ent"],
               "temperature": recorder.figures["ent_reg"]}
    return init, figures, grads, params


def check_cdt(dsrl_train, algorithms):
    data = cdt_windows(np.random.default_rng(SEED))
    init, losses, grads, params = cdt_step(algorithms, data, torch.float32)
    _, losses64, grads64, params64 = cdt_step(algorithms, data, torch.float64)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        save_file(init, tmp / "init.safetensors")
        batch = {k: v.contiguous() for k, v in data.items() if k != "episode_cost"}
        batch["time_steps"] = batch["time_steps"].to(torch.float32)
        save_file(batch, tmp / "batch.safetensors")
        (tmp / "parity.json").write_text(json.dumps({
            "algorithm": "cdt", "obs_dim": OBS, "act_dim": ACT, "episode_len": CDT_EPISODE, "noise_seed": SEED,
            "cdt": list(CDT_SIZES)}))
        subprocess.run([dsrl_train, "parity", str(tmp)], check=True)
        ours = load_file(tmp / "candle.safetensors")
    return compare("cdt", losses, losses64, grads, grads64, params, params64, init, ours)


def main():
    args = sys.argv[1:]
    table = None
    if "--table" in args:
        i = args.index("--table")
        table = args[i + 1]
        del args[i:i + 2]
    dsrl_train = args[0]
    algos = args[1:] or list(PLANS) + ["cdt"]
    stand_in_loggers()
    with contextlib.redirect_stdout(sys.stderr):
        import osrl.algorithms as algorithms
        from fsrl.utils import DummyLogger
    torch.set_num_threads(1)
    results = [check_cdt(dsrl_train, algorithms) if a == "cdt" else check(a, dsrl_train, algorithms, DummyLogger)
               for a in algos]
    if table:
        Path(table).write_text(markdown(results))
    sys.exit(0 if all(r["ok"] for r in results) else 1)


NAMES = {"bcql": "BCQ-Lag", "bearl": "BEAR-Lag", "cpq": "CPQ", "coptidice": "COptiDICE", "cdt": "CDT"}


def markdown(results):
    """The results as README.md's table: per algorithm whether it passed and its largest differences, where, and
    (over the tolerance) how far each side is from float64."""
    def cell(r, kind):
        d, where, f64 = r["largest_relative_difference"][kind], r["where"][kind], r["float64_error"].get(kind)
        if d == 0:  # weights: every change within ULPS float32 steps of the weight (judge above)
            return f"within {ULPS} ulp" if kind == "param" else "0"
        text = f"{d:.1e} (`{where}`)"
        if f64:
            text += f"; float64: candle {f64['candle']:.1e}, PyTorch {f64['pytorch']:.1e}"
        return text
    rows = ["| algorithm | passes | largest loss difference | largest gradient difference "
            "| largest weight-update difference |", "|---|---|---|---|---|"]
    rows += [f"| {NAMES.get(r['algorithm'], r['algorithm'])} | {'yes' if r['ok'] else 'NO'} | {cell(r, 'loss')} "
             f"| {cell(r, 'grad')} | {cell(r, 'param')} |" for r in results]
    return "\n".join(rows) + "\n"


if __name__ == "__main__":
    main()
