"""``bbcity check``: validate a dataset (rig, poses, every image)."""

from __future__ import annotations

from pathlib import Path


def add(sub) -> None:
    """The ``check`` command on the subcommands ``sub``."""
    p = sub.add_parser("check", help="validate a dataset (rig, poses, every image)",
                       description="""Validate rig.json, poses.json, dataset.json and that every image exists, and
                                      what recon needs of the rig and poses (stereo pairs that rectify; a
                                      one-camera capture's stereo partners); with --deep also decode every
                                      image and ground-truth array (sizes, a camera's images not all one
                                      flat colour, depth not all NaN, object ids of the scene). A dataset
                                      that passes --deep runs through recon, build and eval.""")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--deep", action="store_true", help="decode every image and ground-truth array (slow)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Read the dataset (and with --deep every array); print its size. An inconsistent dataset
    raises DataFormatError naming the file and key (exit 2): the checks are those of
    :func:`capture.dataset.load_dataset` (strict: the stages only warn of ground truth that
    dataset.json declares and gt/ lacks), those of :mod:`recon.preflight` (stereo pairs that
    rectify; a one-camera capture's stereo partners) and :meth:`capture.dataset.Dataset.verify`."""
    from capture.dataset import load_dataset
    from recon.pipeline import ReconConfig
    from recon.preflight import check_motion_partners, check_rig_pairs

    ds = load_dataset(args.dataset, strict=True)
    recon = ReconConfig()  # what recon refuses with its defaults, from the rig and poses alone
    check_rig_pairs(ds, recon.max_image_size)
    check_motion_partners(ds, recon.motion)
    if args.deep:
        ds.verify()
    w, h = ds.rig.sizes[0]
    print(f"{ds.root}: {ds.num_frames} frames × {ds.rig.num_cameras} cameras, {w}x{h}, "
          f"ground truth: {'yes' if ds.has_ground_truth else 'no'}")
    return 0
