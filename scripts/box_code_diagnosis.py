"""Where PSSNet's hidden handles go wrong: the decoder, or the box posterior? (results/box_mixture/README.md)

On hidden-handle test mugs, decodes three kinds of box code with the rest of the latent as the model gives it,
and measures the handle of each decoded shape (pssnet_core.evaluation.handles):

1. the flow codes of the boxes the view allows: the mug turned to 8 azimuths of its plausible arc (Alg. 1),
   rest of the latent at the posterior mean -> does the decoder draw the handle where the box says?
2. samples of the model's box posterior (20 per view) -> how often is there a handle at all?
3. those samples' boxes snapped to the nearest rigid cuboid (flow inverse, least-squares box, flow again).
4. the decoder's reach: the flow codes of the mug turned to every ``--reach-step`` degrees all round, by how far
   the box puts the handle from straight behind the mug (seen from the camera), with the rest of the latent at the
   posterior mean, halfway to the prior's mean, and at the prior's mean (0) -> where does the decoder stop drawing
   the handle where the box says, and is it the decoder or the rest of the latent that stops it?

Needs a checkpoint with its flow (it embeds boxes): a training checkpoint, or an export written since exports
keep it (the shipped model's does not). Usage:
    .venv/bin/python scripts/box_code_diagnosis.py --checkpoint runs/pssnet32_large/best.pt --views 24
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from pssnet_core.data.scenes import box_in_grid
from pssnet_core.evaluation.ambiguity_sets import mug_parts, plausible_handle_arc
from pssnet_core.evaluation.handles import HandleGeometry, circular_difference_deg, handle_azimuths, turned
from pssnet_core.evaluation.testsets import load_test_set
from pssnet_core.models.checkpoint import load_checkpoint
from pssnet_core.shapes import shape_of

#: lower edges of the reach measure's bands of |azimuth from straight behind| (degrees)
REACH_BANDS = (0, 30, 60, 90, 120, 150)
#: the reach measure's rests of the latent: the posterior mean scaled by this towards the prior's mean (0)
REACH_RESTS = {"the posterior mean": 1.0, "half the posterior mean": 0.5, "the prior mean": 0.0}
#: corner signs in Shape.box_corners order (binary counting, x fastest)
SIGNS = np.array([[(i & 1) * 2 - 1, ((i >> 1) & 1) * 2 - 1, ((i >> 2) & 1) * 2 - 1] for i in range(8)], float)


def nearest_cuboid(corners: np.ndarray, iterations: int = 10) -> np.ndarray:
    """(8, 3) corners -> the corners of the nearest rigid box: centre + R diag(h) s_i, fitted by alternating
    an orthogonal Procrustes step for R with a least-squares step for the half-extents h."""
    centre = corners.mean(0)
    a = SIGNS.T @ (corners - centre) / 8.0  # = diag(h) R^T for an exact box
    h = np.linalg.norm(a, axis=1)
    for _ in range(iterations):
        u, _, vt = np.linalg.svd(np.diag(h) @ a)
        rt = u @ vt
        h = np.einsum("ij,ij->i", a, rt)
    return centre + (SIGNS * h) @ rt


def decode_handles(model, z: torch.Tensor, view, geometry: HandleGeometry) -> np.ndarray:
    occupancy = (torch.sigmoid(model.decode(z).float()) > 0.5).numpy()[:, 0]
    return handle_azimuths(occupancy, view.grid_pose, view.object_pose, geometry)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--data", default="data/d32/test/mugs")
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--samples", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--reach-step", type=float, default=15.0, help="azimuth step of the reach measure (deg)")
    args = parser.parse_args()
    model, _, extra = load_checkpoint(args.checkpoint)
    model.eval()
    if not model.has_box_latent:
        raise SystemExit("the checkpoint has no box part (PSSNet only)")
    if "flow." in extra["missing_modules"]:
        raise SystemExit(f"{args.checkpoint} was exported without its flow: use its training checkpoint")
    views = [v for v in load_test_set(args.data)[0] if v.meta.get("handle_visible") is False]
    rng = np.random.default_rng(args.seed)
    views = [views[i] for i in sorted(rng.choice(len(views), min(args.views, len(views)), replace=False))]
    generator = torch.Generator().manual_seed(args.seed)
    k = model.box_dim
    rates: dict[str, list[float]] = {"allowed boxes": [], "posterior samples": [], "snapped samples": []}
    errors: list[float] = []
    reach = {rest: {band: [] for band in REACH_BANDS} for rest in REACH_RESTS}
    for view in views:
        shape = shape_of(view.identity)
        arc = plausible_handle_arc(view, view.depth_view, mug_parts(shape)).arc(0.01)
        if len(arc) < 3:
            continue
        geometry = HandleGeometry.of(shape)
        x = torch.from_numpy(view.network_input())[None]
        with torch.inference_mode():
            mu, logvar = model.encode(model.check_input(x))
            wanted = arc[np.linspace(0, len(arc) - 1, 8).round().astype(int)]
            boxes = np.stack([box_in_grid(shape, turned(view.object_pose, a), view.grid_pose, np.eye(4))
                              for a in wanted])
            codes = model.embed_box(model.normalise_box(torch.from_numpy(boxes)))
            got = decode_handles(model, torch.cat([codes, mu[:, k:].expand(len(codes), -1)], 1), view, geometry)
            rates["allowed boxes"].append(float(np.isfinite(got).mean()))
            drawn = np.isfinite(got)
            errors.extend(np.abs(circular_difference_deg(got[drawn], wanted[drawn])).tolist())

            z = model.sample_latents(mu, logvar, args.samples, generator, 1.0)
            rates["posterior samples"].append(float(np.isfinite(decode_handles(model, z, view, geometry)).mean()))
            sampled = model.box_of_code(z[:, :k])
            snapped = np.stack([nearest_cuboid(c) for c in sampled.reshape(-1, 8, 3).numpy()])
            snapped_codes = model.embed_box(model.normalise_box(torch.from_numpy(snapped.reshape(-1, 24)).float()))
            z_snapped = torch.cat([snapped_codes, z[:, k:]], 1)
            rates["snapped samples"].append(float(np.isfinite(decode_handles(model, z_snapped, view, geometry)).mean()))

            # Reach: every azimuth all round, binned by the angle between the box's handle and straight behind.
            camera = np.linalg.inv(view.object_pose)[:2, 3]  # the camera in the mug's frame (handle along +x)
            behind = float(np.degrees(np.arctan2(-camera[1], -camera[0])))
            around = np.arange(-180.0, 180.0, args.reach_step)
            boxes = np.stack([box_in_grid(shape, turned(view.object_pose, a), view.grid_pose, np.eye(4))
                              for a in around])
            codes = model.embed_box(model.normalise_box(torch.from_numpy(boxes)))
            for rest, scale in REACH_RESTS.items():
                z = torch.cat([codes, scale * mu[:, k:].expand(len(codes), -1)], 1)
                got = decode_handles(model, z, view, geometry)
                for wanted_deg, got_deg in zip(around, got, strict=True):
                    away = abs(float(circular_difference_deg(np.array([wanted_deg]), np.array([behind]))[0]))
                    band = max(b for b in REACH_BANDS if away >= b)
                    drawn = bool(np.isfinite(got_deg))
                    error = abs(float(circular_difference_deg(np.array([got_deg]), np.array([wanted_deg]))[0])) \
                        if drawn else float("nan")
                    reach[rest][band].append((drawn, error))
    print(f"{len(rates['allowed boxes'])} hidden-handle views with an arc of 3 azimuths or more")
    for name, values in rates.items():
        print(f"{name:>18}: a handle in {100 * np.mean(values):.0f} % of decoded shapes")
    print(f"allowed boxes: handle {np.mean(errors):.1f} deg (mean) from the azimuth the box was turned to")
    print("reach: box codes of the mug turned all round; angle of the box's handle from straight behind the mug")
    for rest, bands in reach.items():
        print(f" rest of the latent at {rest}:")
        for band, entries in bands.items():
            drawn = [d for d, _ in entries]
            errs = [e for d, e in entries if d]
            print(f"  {band:>3}-{band + 30 if band < 150 else 180:>3} deg: {len(entries):>4} decodes, a handle in "
                  f"{100 * np.mean(drawn):.0f} %, {np.median(errs) if errs else float('nan'):.1f} deg (median) "
                  f"from where the box puts it, within 30 deg in "
                  f"{100 * np.mean([e <= 30 for e in errs]) if errs else 0:.0f} %")


if __name__ == "__main__":
    main()
