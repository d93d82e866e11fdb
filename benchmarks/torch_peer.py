#!/usr/bin/env python
"""A PyTorch peer of the NeLD-BA train step, timed against the JAX step in the same process.

    python benchmarks/torch_peer.py                                  # CPU, eager float32, the cpu budget's sizes
    python benchmarks/torch_peer.py --torch_device=cuda --torch_modes=eager,tf32,compile

torch is not a dependency of neld_jax (nor of its tests): install it beside it to run this (`pip install torch`).

The peer is written as research code usually is: an nn.Module MLP, the surrogate Fourier encoding as a
torch.autograd.Function, torch.optim.Adam. It does the same work per step as the JAX step
(neld_jax.training.train.make_step over one cube), at the same sizes: a uniform batch of rays, per-scan SE(3)
corrections (exp, composed on the right of the initial pose), the cube interval (eq. 7), stratified coarse samples,
NeLD-BA's fine samples in the bin before each coarse sample, one MLP evaluation per sample (the fine pass reuses the
coarse densities, as in JAX; --reevaluate_coarse evaluates the coarse samples again in the fine pass, as a typical
NeRF implementation does), alpha compositing, the L1 range and termination losses of eq. 13, and Adam on the
field and the poses. Left out (negligible work): the learning-rate schedules (constant rates here).

Defaults are the cpu budget's sizes: 512 rays x (32 coarse + 16 fine), width 128, depth 4 (skip at 2), L = 10,
4 view frequencies. Modes: eager (float32), tf32 (CUDA: TF32 matmuls), compile (torch.compile of the loss,
with TF32 on CUDA). Each of --repeats rounds times --steps JAX steps, then --steps steps of each mode; the
figures are medians over the rounds. One JSON line on stdout.
"""

from __future__ import annotations

import json
import logging
import math
import statistics
import sys
import time

import harness  # this folder's benchmarks/harness.py: --out, the machine stamp and the JSON schema
import numpy as np
import train_step  # this folder's benchmarks/train_step.py: the size flags (--rays, --coarse, ...) and its runner
from absl import app, flags

from neld_jax.hugepages import reexec_with_huge_page_malloc

logger = logging.getLogger(__name__)
FLAGS = flags.FLAGS
flags.DEFINE_list("torch_modes", ["eager"], "Peer modes to time: eager, tf32, compile.")
flags.DEFINE_string("torch_device", "cpu", "torch device: cpu or cuda.")
flags.DEFINE_bool("reevaluate_coarse", False, "Fine pass evaluates the MLP on coarse + fine samples (NeRF-style).")
flags.DEFINE_integer("torch_threads", 0, "torch.set_num_threads (0: torch's default).")


def build_peer(torch, sizes: dict, rays_np, T_init_np, device: str, reevaluate_coarse: bool, seed: int = 0):
    """The peer's model, optimiser and step(): all torch objects, built from the benchmark's sizes.

    rays_np: a neld_jax.training.rays.RaySet (numpy); T_init_np: [S, 4, 4]. Returns (step, parameters) where
    step() runs one training step and returns the loss tensor.
    """
    nn, F = torch.nn, torch.nn.functional
    torch.manual_seed(seed)
    dev = torch.device(device)
    L, Ld = sizes["pos_freqs"], sizes["dir_freqs"]
    width, depth, skips = sizes["width"], sizes["depth"], tuple(k for k in sizes["skip_layers"] if k < sizes["depth"])
    num_rays, num_coarse, num_fine = sizes["rays"], sizes["coarse"], sizes["fine"]
    z_low, z_up = 0.3 * train_step.SYNTHETIC_SCALE, 200.0 * train_step.SYNTHETIC_SCALE

    class SurrogateFourier(torch.autograd.Function):
        """[cos(2^k pi x), sin(2^k pi x)]; backward divided by 2^k pi per frequency (eq. 9)."""

        @staticmethod
        def forward(ctx, x, num_freqs):
            scales = 2.0 ** torch.arange(num_freqs, device=x.device, dtype=x.dtype)
            angles = math.pi * (x[:, None, :] * scales[:, None]).reshape(x.shape[0], -1)  # [N, L*D], k-major
            cos, sin = torch.cos(angles), torch.sin(angles)
            ctx.save_for_backward(cos, sin)
            ctx.num_freqs = num_freqs
            return torch.cat([cos, sin], dim=-1)

        @staticmethod
        def backward(ctx, grad):
            cos, sin = ctx.saved_tensors
            n = cos.shape[-1]
            per_feature = -grad[:, :n] * sin + grad[:, n:] * cos
            return per_feature.reshape(cos.shape[0], ctx.num_freqs, -1).sum(dim=1), None

    def encode(x, num_freqs, window=None):
        cos_sin = SurrogateFourier.apply(x, num_freqs)
        if window is not None:
            weights = window.repeat_interleave(x.shape[-1])  # [L*D], k-major like the features
            cos_sin = cos_sin * torch.cat([weights, weights])
        return torch.cat([x, cos_sin], dim=-1)

    class Field(nn.Module):
        def __init__(self):
            super().__init__()
            enc, enc_dir = 3 * (1 + 2 * L), 3 * (1 + 2 * Ld)
            dims = [enc] + [width] * depth
            self.hidden = nn.ModuleList(nn.Linear(dims[i] + (enc if i in skips else 0), width) for i in range(depth))
            self.density_hidden = nn.Linear(width + enc_dir, width // 2)
            self.out = nn.Linear(width // 2, 1)
            nn.init.normal_(self.out.weight, std=1e-2 / math.sqrt(width // 2))
            nn.init.constant_(self.out.bias, math.log(math.expm1(0.1)))  # softplus^-1 of the initial density

        def forward(self, points, view, window):
            encoded = encode(points, L, window)
            h = encoded
            for i, layer in enumerate(self.hidden):
                if i in skips:
                    h = torch.cat([h, encoded], dim=-1)
                h = F.relu(layer(h))
            h = F.relu(self.density_hidden(torch.cat([h, encode(view, Ld)], dim=-1)))
            return F.softplus(self.out(h))[:, 0]

    def se3_exp(xi):
        """[S, 6] (rho, omega) -> [S, 4, 4], Rodrigues with series near 0."""
        rho, omega = xi[:, :3], xi[:, 3:]
        theta2 = (omega * omega).sum(-1)
        small = theta2 < 1e-8
        theta = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
        a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
        b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / torch.where(small, 1.0, theta2))
        safe2 = torch.where(small, torch.ones_like(theta2), theta2)
        c = torch.where(small, 1 / 6 - theta2 / 120, (theta - torch.sin(theta)) / (safe2 * theta))
        zero = torch.zeros_like(theta2)
        K = torch.stack(
            [zero, -omega[:, 2], omega[:, 1], omega[:, 2], zero, -omega[:, 0], -omega[:, 1], omega[:, 0], zero], -1
        ).reshape(-1, 3, 3)
        eye = torch.eye(3, device=xi.device, dtype=xi.dtype).expand_as(K)
        K2 = K @ K
        R = eye + a[:, None, None] * K + b[:, None, None] * K2
        V = eye + b[:, None, None] * K + c[:, None, None] * K2
        t = (V @ rho[:, :, None])[:, :, 0]
        top = torch.cat([R, t[:, :, None]], dim=-1)
        bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], device=xi.device, dtype=xi.dtype).expand(xi.shape[0], 1, 4)
        return torch.cat([top, bottom], dim=1)

    def cube_interval(o, d):
        inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
        t1, t2 = (-1.0 - o) * inv, (1.0 - o) * inv
        near = torch.minimum(t1, t2).amax(-1)
        far = torch.maximum(t1, t2).amin(-1)
        z_near, z_far = torch.clamp(near, min=z_low), torch.clamp(far, max=z_up)
        ok = (far > torch.clamp(near, min=0.0)) & (z_near < z_far)
        return torch.where(ok, z_near, torch.full_like(near, z_low)), torch.where(ok, z_far, torch.full_like(far, z_up))

    def composite(sigma, z, z_far):
        deltas = torch.cat([z[:, 1:] - z[:, :-1], torch.clamp(z_far[:, None] - z[:, -1:], min=0.0)], dim=-1)
        optical = sigma * deltas
        alpha = -torch.expm1(-optical)
        in_front = torch.cat([torch.zeros_like(optical[:, :1]), torch.cumsum(optical[:, :-1], dim=-1)], dim=-1)
        weights = torch.exp(-in_front) * alpha
        return weights, (weights * z).sum(-1)

    def fine_before(z_coarse, weights, z_near):
        bin_start = torch.cat([z_near[:, None], z_coarse[:, :-1]], dim=-1)
        total = weights.sum(-1, keepdim=True)
        pdf = torch.where(total > 0, weights / total.clamp(min=1e-30), torch.full_like(weights, 1 / weights.shape[-1]))
        cdf = torch.cumsum(pdf, -1)
        u = (torch.arange(num_fine, device=dev) + torch.rand(z_coarse.shape[0], num_fine, device=dev)) / num_fine
        idx = torch.searchsorted(cdf.contiguous(), u.contiguous(), right=True).clamp(max=cdf.shape[-1] - 1)
        cdf_before = torch.gather(cdf - pdf, 1, idx)
        frac = ((u - cdf_before) / torch.gather(pdf, 1, idx).clamp(min=1e-12)).clamp(0.0, 1.0)
        lo, hi = torch.gather(bin_start, 1, idx), torch.gather(z_coarse, 1, idx)
        return torch.sort(lo + frac * (hi - lo), dim=-1).values

    def densities(field, o, d, z, window):
        r, n = z.shape
        points = (o[:, None, :] + z[..., None] * d[:, None, :]).reshape(-1, 3)
        view = d[:, None, :].expand(r, n, 3).reshape(-1, 3)
        return field(points, view, window).reshape(r, n)

    def losses(weights, depth, z, ranges):
        l_range = (depth - ranges).abs().mean()
        beyond = z > ranges[:, None]
        idx = beyond.to(torch.int8).argmax(-1, keepdim=True)
        nll = -torch.log(torch.gather(weights, 1, idx)[:, 0].clamp(min=1e-10))
        valid = beyond.any(-1).to(nll.dtype)
        return l_range + (nll * valid).sum() / valid.sum().clamp(min=1.0)

    field = Field().to(dev)
    poses = torch.zeros(T_init_np.shape[0], 6, device=dev, requires_grad=True)
    directions = torch.as_tensor(np.asarray(rays_np.directions), device=dev)
    ranges_all = torch.as_tensor(np.asarray(rays_np.ranges), device=dev)
    scan_all = torch.as_tensor(np.asarray(rays_np.scan_index), device=dev).long()
    T_init = torch.as_tensor(np.asarray(T_init_np, np.float32), device=dev)
    optimizer = torch.optim.Adam([{"params": field.parameters(), "lr": 5e-3}, {"params": [poses], "lr": 1e-3}])
    alpha_c2f = torch.tensor(float(L) / 2, device=dev)  # mid-way through the coarse-to-fine window

    def loss_fn(idx):
        window = 0.5 * (1 - torch.cos(math.pi * torch.clamp(alpha_c2f - torch.arange(L, device=dev), 0.0, 1.0)))
        T = (T_init @ se3_exp(poses))[scan_all[idx]]  # a right correction in the scan's frame, as in JAX
        o, d = T[:, :3, 3], (T[:, :3, :3] @ directions[idx][:, :, None])[:, :, 0]
        ranges = ranges_all[idx]
        with torch.no_grad():
            z_near, z_far = cube_interval(o, d)
            edges = torch.linspace(0, 1, num_coarse + 1, device=dev)
            span = (z_far - z_near)[:, None]
            jitter = torch.rand(o.shape[0], num_coarse, device=dev)
            z_coarse = z_near[:, None] + span * (edges[:-1] + (edges[1:] - edges[:-1]) * jitter)
        sigma_coarse = densities(field, o, d, z_coarse, window)
        weights_c, depth_c = composite(sigma_coarse, z_coarse, z_far)
        with torch.no_grad():
            z_new = fine_before(z_coarse, weights_c.detach(), z_near)
        if reevaluate_coarse:
            z_fine = torch.sort(torch.cat([z_coarse, z_new], -1), dim=-1).values
            sigma_fine = densities(field, o, d, z_fine, window)
        else:
            z_fine, order = torch.sort(torch.cat([z_coarse, z_new], -1), dim=-1)
            sigma_new = densities(field, o, d, z_new, window)
            sigma_fine = torch.gather(torch.cat([sigma_coarse, sigma_new], -1), 1, order)
        weights_f, depth_f = composite(sigma_fine, z_fine, z_far)
        return 0.1 * losses(weights_c, depth_c, z_coarse, ranges) + losses(weights_f, depth_f, z_fine, ranges)

    compiled = {"fn": loss_fn}

    def step():
        idx = torch.randint(0, ranges_all.shape[0], (num_rays,), device=dev)
        optimizer.zero_grad(set_to_none=True)
        loss = compiled["fn"](idx)
        loss.backward()
        optimizer.step()
        return loss

    def use_compile():
        compiled["fn"] = torch.compile(loss_fn)

    return step, use_compile


def time_torch(torch, step, n: int, device: str) -> tuple[float, float]:
    """(wall seconds, process CPU seconds) of n peer steps."""
    t0, c0 = time.perf_counter(), time.process_time()
    loss = None
    for _ in range(n):
        loss = step()
    float(loss.detach())  # waits for the device
    if device == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - t0, time.process_time() - c0


def main(argv):
    del argv
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
    try:
        import torch
    except ImportError:
        raise app.UsageError("torch is not installed (pip install torch); it is not a dependency of neld_jax")
    if FLAGS.torch_threads:
        torch.set_num_threads(FLAGS.torch_threads)
    config, sizes = train_step.resolve_sizes()
    if sizes["guided"]:
        raise app.UsageError("the peer has no range-guided samples: use --guided=0")
    modes = [m.strip() for m in FLAGS.torch_modes if m.strip()]
    unknown = set(modes) - {"eager", "tf32", "compile"}
    if unknown:
        raise app.UsageError(f"unknown --torch_modes {sorted(unknown)}: eager, tf32, compile")
    device = FLAGS.torch_device

    runner = train_step.StepRunner(
        config, sizes, FLAGS.steps * FLAGS.repeats + 2, FLAGS.scans, FLAGS.rays_per_scan, FLAGS.seed
    )
    jax_loss = float(runner.run(1)["loss"])
    from neld_jax.training.rays import sphere_scene_rays

    rays_np, T_np = sphere_scene_rays(FLAGS.scans, FLAGS.rays_per_scan, FLAGS.seed)  # the JAX runner's rays
    peers, warm = {}, {}
    for mode in modes:
        step, use_compile = build_peer(torch, sizes, rays_np, T_np, device, FLAGS.reevaluate_coarse, FLAGS.seed)
        tf32 = mode in ("tf32", "compile") and device == "cuda"
        if device == "cuda":
            torch.backends.cuda.matmul.allow_tf32 = tf32
        if mode == "compile":
            use_compile()
        t0 = time.perf_counter()
        warm[mode] = {"loss_after_warmup": float(step().detach()), "warmup_s": time.perf_counter() - t0}
        for _ in range(2):
            step()
        peers[mode] = (step, tf32)

    rounds = []
    for _ in range(max(FLAGS.repeats, 1)):
        jax_s, _, jax_cpu_s = train_step.median_seconds(lambda: runner.run(FLAGS.steps), 1)
        entry = {"jax_steps_per_s": FLAGS.steps / jax_s, "jax_cpu_ms_per_step": 1e3 * jax_cpu_s / FLAGS.steps}
        for mode, (step, tf32) in peers.items():
            if device == "cuda":
                torch.backends.cuda.matmul.allow_tf32 = tf32
            wall_s, cpu_s = time_torch(torch, step, FLAGS.steps, device)
            entry[f"torch_{mode}_steps_per_s"] = FLAGS.steps / wall_s
            entry[f"torch_{mode}_cpu_ms_per_step"] = 1e3 * cpu_s / FLAGS.steps
            entry[f"jax_over_torch_{mode}"] = entry["jax_steps_per_s"] / entry[f"torch_{mode}_steps_per_s"]
            entry[f"cpu_jax_over_torch_{mode}"] = entry[f"torch_{mode}_cpu_ms_per_step"] / entry["jax_cpu_ms_per_step"]
        rounds.append(entry)
    median = lambda key: statistics.median(r[key] for r in rounds)  # noqa: E731
    jax_rate = median("jax_steps_per_s")
    torch_rates = {mode: median(f"torch_{mode}_steps_per_s") for mode in peers}
    record = {
        "benchmark": "torch_peer",
        "jax_steps_per_s": jax_rate,
        "torch_steps_per_s": torch_rates,
        "jax_over_torch": {mode: jax_rate / rate for mode, rate in torch_rates.items()},  # ratio of the medians
        "jax_over_torch_round_median": {mode: median(f"jax_over_torch_{mode}") for mode in peers},
        # process CPU time per step (all threads): steadier than wall time where other jobs share the cores
        "cpu_jax_over_torch": {mode: median(f"cpu_jax_over_torch_{mode}") for mode in peers},
        "rounds": rounds,
        "jax_loss_after_warmup": jax_loss,
        "torch_warmup": warm,
        **train_step.device_info(),
        "torch_version": torch.__version__,
        "torch_device": (
            str(torch.cuda.get_device_name(0)) if device == "cuda" else f"cpu ({torch.get_num_threads()} threads)"
        ),
        "config": {
            **sizes,
            "skip_layers": list(sizes["skip_layers"]),
            "steps": FLAGS.steps,
            "repeats": FLAGS.repeats,
            "scans": FLAGS.scans,
            "rays_per_scan": FLAGS.rays_per_scan,
            "reevaluate_coarse": FLAGS.reevaluate_coarse,
            "modes": modes,
        },
    }
    print(json.dumps(record), flush=True)
    harness.write(FLAGS.out, record)


if __name__ == "__main__":
    FLAGS.set_default("dir_freqs", 4)  # the peer's sizes: 4 view frequencies
    reexec_with_huge_page_malloc()  # the same allocator for both (neld_jax/hugepages.py)
    app.run(main)
