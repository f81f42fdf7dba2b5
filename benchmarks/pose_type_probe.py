"""Does a pose network's pooled global feature tell the pallet types apart? (a linear probe)

    python benchmarks/pose_type_probe.py --ckpt runs/mt/last.pt --config edge2-dilated --data DIR [DIR ...] \
        --cache-dir runs/pose3/run/cache --seed 13 --out benchmarks/results/pallet-types/probe.md

The pose stage's samples of the datasets (`train_pose.load_pose_data`, split by frame as the trainer splits them),
each sample's global feature (the mean over points of `conv6`'s output, what the pose heads see), then a linear
classifier and one with a hidden layer of 128, trained on the training frames' features with class-balanced cross
entropy, scored on the held-out frames: accuracy and top-2 accuracy per type. A type head on that feature could
only be as good as the probe.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def global_features(ckpt: Path, config: str, data: list[str], cache_dir: Path, seed: int, threads: int):
    """(features (n, C), type row per sample (n,), train indexes, held-out indexes, type names by row)."""
    import torch

    from pallet6d.export.config import get_config
    from pallet6d.export.train_data import AugmentConfig
    from pallet6d.export.train_loop import load_checkpoint
    from pallet6d.export.train_pose import PoseTrainer, load_pose_data

    torch.set_num_threads(threads)
    cfg = get_config(config)
    pd = load_pose_data(cfg, data, 2, seed, AugmentConfig(), cache_dir, 0.1, None, False)
    trainer = PoseTrainer(cfg, pd)
    weights = load_checkpoint(ckpt)
    trainer.fusion.load_state_dict(weights["fusion"])
    trainer.pose.load_state_dict(weights["pose"])
    trainer.fusion.eval()
    trainer.pose.eval()
    seen = {}
    trainer.pose.conv6.register_forward_hook(lambda m, i, o: seen.__setitem__("g", torch.relu(o).mean(2)))
    idx_all = np.concatenate([pd.train_idx, pd.val_idx])
    feats = np.zeros((len(pd.samples), cfg.pose.global_dims[1]), np.float32)
    with torch.no_grad():
        for i in range(0, len(idx_all), 64):
            idx = idx_all[i:i + 64]
            trainer.forward_loss(idx)
            feats[idx] = seen["g"].numpy()
    ids = np.array(sorted(pd.type_names))
    return feats, np.searchsorted(ids, pd.samples.obj_id), pd.train_idx, pd.val_idx, [pd.type_names[int(o)] for o in ids]


def probe(feats, rows, train, val, hidden: int, seed: int, epochs: int = 60, lr: float = 1e-3) -> np.ndarray:
    """Class probabilities of the held-out samples from a classifier trained on the training ones (AdamW, batches of
    256). :return: (len(val), T)."""
    import torch

    torch.manual_seed(seed)
    mu, sd = feats[train].mean(0), feats[train].std(0) + 1e-6
    x, y = torch.from_numpy((feats - mu) / sd), torch.from_numpy(rows).long()
    n_types = int(rows.max()) + 1
    counts = np.bincount(rows[train], minlength=n_types)
    weight = torch.tensor(counts.sum() / (n_types * np.maximum(counts, 1)), dtype=torch.float32)
    net = torch.nn.Linear(x.shape[1], n_types) if hidden == 0 else torch.nn.Sequential(
        torch.nn.Linear(x.shape[1], hidden), torch.nn.ReLU(), torch.nn.Dropout(0.2), torch.nn.Linear(hidden, n_types))
    opt = torch.optim.AdamW(net.parameters(), lr, weight_decay=1e-3)
    order = torch.from_numpy(train)
    for _ in range(epochs):
        net.train()
        perm = order[torch.randperm(len(order))]
        for i in range(0, len(perm), 256):
            b = perm[i:i + 256]
            loss = torch.nn.functional.cross_entropy(net(x[b]), y[b], weight=weight)
            opt.zero_grad()
            loss.backward()
            opt.step()
    net.eval()
    with torch.no_grad():
        return torch.softmax(net(x[torch.from_numpy(val)]), 1).numpy()


def report(feats, rows, train, val, names, seed: int, title: str) -> str:
    """Markdown: each probe's held-out accuracy and top-2 accuracy, overall and per type."""
    lines = [f"# Pallet type from the pose network's global feature: {title}", "",
             f"{len(train)} training samples, {len(val)} held out; class-balanced cross entropy, 60 epochs.", ""]
    yv = rows[val]
    for hidden in (0, 128):
        p = probe(feats, rows, train, val, hidden, seed)
        pred, top2 = p.argmax(1), (np.argsort(-p, 1)[:, :2] == yv[:, None]).any(1)
        lines += [f"## {'linear' if hidden == 0 else f'hidden layer of {hidden}'}: held-out accuracy "
                  f"{np.mean(pred == yv):.3f}, top-2 {top2.mean():.3f}", "",
                  "| type | held-out samples | accuracy | top-2 |", "|---|---|---|---|"]
        for k, name in enumerate(names):
            m = yv == k
            if m.any():
                lines.append(f"| {name} | {m.sum()} | {np.mean(pred[m] == k):.2f} | {top2[m].mean():.2f} |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ckpt", type=Path, required=True, help="a pose (or merged) training checkpoint")
    ap.add_argument("--config", default="edge2-dilated")
    ap.add_argument("--data", nargs="+", required=True, help="BOP datasets, as given to `pallet6d train pose`")
    ap.add_argument("--cache-dir", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=0, help="the training run's seed (its frame split)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)

    feats, rows, train, val, names = global_features(args.ckpt, args.config, args.data, args.cache_dir, args.seed,
                                                     args.threads)
    text = report(feats, rows, train, val, names, args.seed, str(args.ckpt))
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
