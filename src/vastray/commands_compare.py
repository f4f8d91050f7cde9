"""``vastray compare``: the error of one image against another."""

from __future__ import annotations

import argparse

from vastray.render.imageio import image_error, read_image
from vastray.scene.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    c = sub.add_parser(
        "compare", help="print MSE, PSNR and max difference of two images",
        description="Compare two images (.exr or .npy, same size).",
        epilog="example:\n  vastray compare render.exr reference.exr",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    c.add_argument("image")
    c.add_argument("reference")
    c.set_defaults(func=run_compare)


def run_compare(args: argparse.Namespace) -> int:
    image, reference = read_image(args.image), read_image(args.reference)
    if image.shape != reference.shape:
        raise InputError(args.image, f"size {image.shape} differs from the reference's "
                                     f"{reference.shape}")
    err = image_error(image, reference)
    psnr = "inf" if err["psnr_db"] is None else f"{err['psnr_db']:.3f}"
    print(f"mse={err['mse']:.6g} psnr_db={psnr} max_abs_diff={err['max_abs_diff']:.6g}")
    return 0
