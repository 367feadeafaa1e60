"""``pssnet train``, ``export-model``, ``posterior`` and ``fit-box-head`` subcommands (runnable alone: :func:`main`)."""

from __future__ import annotations

import argparse
import signal
import sys

from pssnet_core.data.store import DatasetError, DatasetReader
from pssnet_core.models.base import PRECISIONS
from pssnet_core.models.checkpoint import CheckpointError, export_checkpoint, read_checkpoint
from pssnet_core.models.config import ConfigError
from pssnet_core.models.registry import model_names
from pssnet_core.training.distributed import DistributedError, StopFlag
from pssnet_core.training.trainer import BEST_METRICS, TrainConfig, Trainer, TrainingError


def register(subparsers: argparse._SubParsersAction) -> None:
    """Adds ``train``, ``export-model``, ``posterior`` and ``fit-box-head`` to the ``pssnet`` command line."""
    p = subparsers.add_parser(
        "train", help="train a completion model (pssnet, vae, vae_gan, recgan) on a dataset directory",
        description="Trains a model on a dataset written by `pssnet dataset build`; writes last.pt (resumable), "
                    "best.pt, CSV logs and loss_curves.png to --out. Data parallel across processes and machines "
                    "under torchrun: `torchrun --nproc-per-node K -m pssnet_core train ...` (gloo on CPU, NCCL "
                    "on GPUs; rank 0 writes --out). Turned twins (--twin-rate): `pssnet dataset twins --data DIR` "
                    "first, then e.g. `--init-from RUN/best.pt --twin-rate 0.5` to fine-tune a PSSNet with them.")
    p.add_argument("--model", required=True, choices=model_names())
    p.add_argument("--data", required=True,
                   help="training dataset directory; several joined by commas are read as one (e.g. mugs,ycb)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--val-data", default=None, help="validation dataset (default: a slice of --data)")
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--max-minutes", type=float, default=None, help="wall-clock budget of this invocation")
    p.add_argument("--max-steps", type=int, default=None,
                   help="optimiser-step budget of the run (the fair budget on a shared machine)")
    p.add_argument("--batch-size", type=int, default=16,
                   help="views per step and rank (paper: 16); under torchrun a step trains on ranks x this")
    p.add_argument("--lr", type=float, default=1e-3,
                   help="main Adam learning rate (paper: 1e-3), for the mean loss of the whole step's batch; not "
                        "scaled with the number of ranks")
    p.add_argument("--device", default="cpu", help="cpu or cuda (under torchrun each rank takes cuda:LOCAL_RANK)")
    p.add_argument("--precision", default="auto", choices=PRECISIONS,
                   help="auto: bf16 autocast where the hardware has native bf16 (AVX512-BF16/AMX, CUDA), else fp32")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    p.add_argument("--init-from", default=None, metavar="CHECKPOINT",
                   help="warm start a new run: from another run's last.pt (weights + optimiser states) or best.pt "
                        "(weights), or from an inference-only export (weights), all keeping PSSNet's flow, which "
                        "their decoder was trained against (no flow pre-training); an export written before exports "
                        "kept the flow (the shipped model) gets a new one pre-trained")
    p.add_argument("--val-every", type=int, default=0, help="validate every N steps (0: every epoch)")
    p.add_argument("--val-max-samples", type=int, default=512)
    p.add_argument("--val-slice", type=int, default=16, help="inputs for the quick best-accuracy")
    p.add_argument("--val-num-samples", type=int, default=8, help="samples per input for best-accuracy")
    p.add_argument("--best-metric", default="val_bce", choices=sorted(BEST_METRICS))
    p.add_argument("--log-every", type=int, default=10)
    p.add_argument("--model-config", default=None,
                   help="YAML of model config overrides, e.g. 'channels: [8, 16, 32, 64]' or 'flow_lr: 1e-4'")
    p.add_argument("--twin-rate", type=float, default=None, metavar="P",
                   help="PSSNet: decode a share P of each batch from a turned twin's box code (the view's mug turned "
                        "about its axis; `pssnet dataset twins` builds them) with the rest of the latent still from "
                        "the view, against the twin's grid. Why: box code and rest otherwise always agree, and the "
                        "rest learns to veto handles the box code puts at the edges of what the view allows (drawn "
                        "21-43 %% of the time at the posterior mean, 98-100 %% with the rest at 0); twins make the "
                        "decoder follow the box code. Overrides the model config's twin_rate (also that of "
                        "--init-from or --resume); views without twins (ycb, no handle) use their own box and grid")
    p.add_argument("--half-checkpoint", action="store_true", help="store best.pt as float16")
    p.add_argument("--no-progress", action="store_true", help="no tqdm bars")
    p.set_defaults(func=_train)

    e = subparsers.add_parser(
        "export-model", help="compact checkpoint for shipping (fp16, no discriminator/optimiser state; PSSNet keeps "
                             "its flow)")
    e.add_argument("src", help="checkpoint written by `pssnet train` (best.pt)")
    e.add_argument("dst", help="output file, e.g. pssnet_core/checkpoints/default_pssnet_32.pt")
    e.add_argument("--fp32", action="store_true", help="keep float32 weights")
    e.add_argument("--box-temperature", type=float, default=None,
                   help="record the box temperature calibrated for this model (PSSNet; the default of its users)")
    e.add_argument("--keep-training-modules", action="store_true",
                   help="keep the GAN discriminator (needed to fine-tune a VAE-GAN or 3D-RecGAN++ from the export)")
    e.set_defaults(func=_export)

    q = subparsers.add_parser(
        "posterior", help="posterior-mean BCE/IoU per split (memorisation gap) and box-posterior width",
        description="For each checkpoint and dataset: BCE per voxel and IoU of decode(mu), the BCE relative to "
                    "the dataset labelled 'train', and the mean posterior sigma of the box dims on mug views "
                    "with the handle hidden and visible (see pssnet_core/training/posterior.py).")
    q.add_argument("--checkpoints", required=True, help="comma-separated checkpoints (best.pt or exports)")
    q.add_argument("--labels", default=None, help="comma-separated names for the checkpoints")
    q.add_argument("--data", action="append", required=True, metavar="LABEL=DIR[,DIR]",
                   help="a dataset to measure, repeatable; label one 'train' to get the gap ratios")
    q.add_argument("--max-views", type=int, default=None, help="views per dataset, spread evenly (default all)")
    q.add_argument("--threads", type=int, default=2)
    q.add_argument("--out", default=None, help="directory for posterior.txt and posterior.json")
    q.set_defaults(func=_posterior)

    b = subparsers.add_parser(
        "fit-box-head", help="fit a mixture box posterior onto a trained PSSNet (encoder, decoder, flow frozen)",
        description="Encodes training views with a trained PSSNet, fits a K-component mixture to the flow codes "
                    "of their true boxes, and writes a checkpoint with that head (pssnet_core/training/box_head.py).")
    b.add_argument("--checkpoint", required=True, help="PSSNet training checkpoint (best.pt; needs the flow)")
    b.add_argument("--data", required=True, help="training dataset directories, comma-joined")
    b.add_argument("--out", required=True, help="checkpoint to write, e.g. runs/pssnet32_mix/best.pt")
    b.add_argument("--components", type=int, default=16)
    b.add_argument("--hidden", type=int, default=256)
    b.add_argument("--max-views", type=int, default=None, help="training views to encode (default all)")
    b.add_argument("--steps", type=int, default=4000)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--threads", type=int, default=2)
    b.set_defaults(func=_fit_box_head)


def _posterior(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from pssnet_core.models.checkpoint import load_checkpoint
    from pssnet_core.training.posterior import format_table, posterior_stats, stats_dict
    from pssnet_core.training.trainer import resolve_context

    checkpoints = [c for c in args.checkpoints.split(",") if c]
    labels = args.labels.split(",") if args.labels else [Path(c).parent.name or c for c in checkpoints]
    if len(labels) != len(checkpoints):
        print("pssnet posterior: error: --labels must name every checkpoint", file=sys.stderr)
        return 2
    datasets = []
    for item in args.data:
        label, sep, path = item.partition("=")
        if not sep or not label or not path:
            print(f"pssnet posterior: error: --data wants LABEL=DIR[,DIR], got {item!r}", file=sys.stderr)
            return 2
        datasets.append((label, path))
    try:
        import torch

        torch.set_num_threads(args.threads)
        ctx = resolve_context("cpu", "auto")
        readers = [(label, DatasetReader(path)) for label, path in datasets]
        rows = []
        for label, path in zip(labels, checkpoints, strict=True):
            model, _, _ = load_checkpoint(path)
            model.to_fast_layout()
            rows.extend((label, posterior_stats(model, reader, name, ctx, args.max_views))
                        for name, reader in readers)
    except (CheckpointError, DatasetError, ValueError) as error:
        print(f"pssnet posterior: error: {error}", file=sys.stderr)
        return 2
    table = format_table(rows)
    print(table)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "posterior.txt").write_text(table + "\n")
        (out / "posterior.json").write_text(json.dumps(stats_dict(rows), indent=1))
        print(f"wrote {out / 'posterior.txt'} and posterior.json")
    return 0


def _train(args: argparse.Namespace) -> int:
    try:
        cfg = TrainConfig(model=args.model, data=args.data, out=args.out, val_data=args.val_data,
                          epochs=args.epochs, max_minutes=args.max_minutes, max_steps=args.max_steps,
                          batch_size=args.batch_size,
                          lr=args.lr, device=args.device, precision=args.precision, threads=args.threads,
                          seed=args.seed, resume=args.resume, init_from=args.init_from, val_every=args.val_every,
                          val_max_samples=args.val_max_samples, val_slice=args.val_slice,
                          val_num_samples=args.val_num_samples, best_metric=args.best_metric,
                          log_every=args.log_every, model_config=args.model_config, twin_rate=args.twin_rate,
                          half_checkpoint=args.half_checkpoint, progress=not args.no_progress)
        # SIGTERM (kill, a job scheduler, a background job whose SIGINT the shell ignores) stops like Ctrl-C, at
        # the next step boundary: last.pt is saved and --resume continues.
        with StopFlag((signal.SIGTERM,)) as stop:
            summary = Trainer(cfg).fit(stop)
    except (TrainingError, DatasetError, ConfigError, CheckpointError, DistributedError) as error:
        print(f"pssnet train: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    if summary["rank"]:
        return 0  # rank 0 reports for the run
    val = summary["last_validation"]
    print(f"done: {summary['steps']} steps, {summary['elapsed_s'] / 60:.1f} min ({summary['stopped_by']}), "
          f"{summary['precision']} on {summary['device']}; last validation: bce {val['val_bce']:.4f}, "
          f"IoU {val['val_iou']:.3f}, best-acc {val['val_best_acc_mm']:.2f} mm; checkpoints in {args.out}"
          + (f" ({summary['world_size']} ranks, {summary['global_batch']} views per step)"
             if summary["world_size"] > 1 else ""))
    return 0


def _fit_box_head(args: argparse.Namespace) -> int:
    from pssnet_core.training.box_head import BoxHeadFitConfig, fit_box_head

    try:
        fit_box_head(BoxHeadFitConfig(checkpoint=args.checkpoint, data=args.data, out=args.out,
                                      components=args.components, hidden=args.hidden, max_views=args.max_views,
                                      steps=args.steps, seed=args.seed, threads=args.threads))
    except (CheckpointError, DatasetError, ValueError) as error:
        print(f"pssnet fit-box-head: error: {error}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}")
    return 0


def _export(args: argparse.Namespace) -> int:
    try:
        path = export_checkpoint(args.src, args.dst, half=not args.fp32,
                                 inference_only=not args.keep_training_modules, box_temperature=args.box_temperature)
        read_checkpoint(path)
    except CheckpointError as error:
        print(f"pssnet export-model: error: {error}", file=sys.stderr)
        return 2
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Standalone entry (``python -m pssnet_core.training.cli train ...``): works on machines without the
    dataset/evaluation dependencies (open3d, trimesh, cv2) that the full ``pssnet`` CLI imports."""
    parser = argparse.ArgumentParser(prog="python -m pssnet_core.training.cli")
    register(parser.add_subparsers(dest="command", required=True, metavar="COMMAND"))
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
