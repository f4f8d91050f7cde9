"""``vastray data fetch``: a small set of real sample meshes and volumes from their public homes,
each verified by its SHA-256 before it is kept."""

from __future__ import annotations

import argparse
import hashlib
import shutil
import sys
import tempfile
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

from vastray.scene.errors import InputError
from vastray.scene.filemode import publish_mode


@dataclass(frozen=True)
class Sample:
    name: str
    url: str
    sha256: str
    size: int
    what: str


_VTK_DATA = "https://raw.githubusercontent.com/pyvista/vtk-data/master/Data/"
_COMMON_3D = "https://raw.githubusercontent.com/alecjacobson/common-3d-test-models/master/data/"

#: The sample set: real scans and a simulation volume, small enough to fetch in seconds.
SAMPLES = [
    Sample("stanford_bunny.ply", _VTK_DATA + "bunny.ply",
           "442bdd8f35bf107005424bbd60100358cd57fa4711640766a5802a17d58f98ad", 3033235,
           "Stanford bunny scan (Turk & Levoy 1994), 69,451 triangles; Stanford 3D Scanning "
           "Repository terms: research use, credit the Stanford Computer Graphics Laboratory"),
    Sample("lucy_100k.ply", _VTK_DATA + "lucy.ply",
           "c57a95174c3c24d87c1ce8b44f48cbf0a5fcab47ce938880ec2acd497a478eb3", 1899711,
           "decimated Stanford Lucy scan, 99,970 triangles; Stanford terms as above"),
    Sample("turbine_blade_199k.ply", _VTK_DATA + "turbineblade.ply",
           "c2850452c86e3076e0d70f77859bee942c096153f687c66b85549f3e52d809cb", 3781928,
           "CT isosurface of a turbine blade, 199,034 triangles; VTKData (BSD-3 notice)"),
    Sample("spot.obj", _COMMON_3D + "spot.obj",
           "0738b5e8608fed74e5e8c7aa8dd0af97b4b74f9f6cbf7aac84cd7e40b2e44a75", 330624,
           "Keenan Crane's Spot, 5,856 triangles; public domain"),
    Sample("fandisk.obj", _COMMON_3D + "fandisk.obj",
           "ea5bab2fbf545b1915f0d9faf6cc61ff8c18e0d8174ad61f8e35de15d8f6e3f8", 379559,
           "Hoppe's fandisk CAD part, 12,946 triangles"),
]

FETCH_EPILOG = """\
example:
  vastray data fetch -o samples
  vastray partition samples/stanford_bunny.ply -o bunny.store --grid 2x2x2
  vastray render bunny.store -o bunny.exr --png bunny.png

Files already present with the right checksum are kept; one that differs (edited, say) is
replaced only with --force. A download whose checksum differs is deleted and reported.
--from DIR copies from a local mirror (a cluster without internet) with the same checks.
"""


def register(sub: argparse._SubParsersAction) -> None:
    data = sub.add_parser("data", help="fetch real sample meshes to try vastray on",
                          description="Sample data: real scanned meshes from their public "
                                      "homes, verified by SHA-256.")
    actions = data.add_subparsers(dest="action", metavar="ACTION", required=True)
    fetch = actions.add_parser("fetch", help="download the sample meshes",
                               description="Download the sample meshes into a folder.",
                               epilog=FETCH_EPILOG,
                               formatter_class=argparse.RawDescriptionHelpFormatter)
    fetch.add_argument("-o", "--output", default="vastray-samples",
                       help="folder to put them in (default: %(default)s)")
    fetch.add_argument("--from", dest="mirror", metavar="DIR",
                       help="copy from this folder instead of downloading")
    fetch.add_argument("--only", nargs="+", metavar="NAME",
                       choices=[s.name for s in SAMPLES], help="fetch only these files")
    fetch.add_argument("--timeout", type=float, default=60.0,
                       help="seconds a download may stall (default: %(default)s)")
    fetch.add_argument("--force", action="store_true",
                       help="replace a file of a sample's name that differs from the sample")
    fetch.set_defaults(func=cmd_fetch)
    actions.add_parser("list", help="list the samples").set_defaults(func=cmd_list)


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def fetch_sample(sample: Sample, folder: Path, mirror: Path | None = None,
                 timeout: float = 60.0, base_url: str | None = None,
                 force: bool = False) -> tuple[Path, bool]:
    """Bring one sample into ``folder``; returns (path, whether it was fetched now).

    Parameters
    ----------
    mirror : a local folder to copy from instead of the URL.
    base_url : replaces the URL's folder (tests serve files from loopback).
    force : replace a file of the sample's name whose content differs from the sample.

    Raises
    ------
    InputError
        The source is unreachable or the checksum differs (nothing is left behind), or a
        different file is in the way without ``force``.
    """
    target = folder / sample.name
    if target.is_file() and sha256_of(target) == sample.sha256:
        return target, False
    if target.exists() and not (force and target.is_file()):
        raise InputError(target, "is in the way: it differs from the sample (edited?); move "
                                 "it, or give --force to replace it" if target.is_file() else
                         "is in the way and not a file")
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{sample.name}.", dir=folder)
    tmp = Path(tmp_name)
    try:
        with open(fd, "wb") as out:
            if mirror is not None:
                source = mirror / sample.name
                if not source.is_file():
                    raise InputError(source, "not found in the mirror folder")
                with open(source, "rb") as src:
                    shutil.copyfileobj(src, out)
            else:
                url = sample.url if base_url is None else base_url + sample.name
                try:
                    with urllib.request.urlopen(url, timeout=timeout) as response:
                        shutil.copyfileobj(response, out)
                except (urllib.error.URLError, OSError) as exc:
                    raise InputError(url, f"download failed ({exc}); without internet, copy "
                                          "the samples from a local mirror: --from DIR") from None
        got = sha256_of(tmp)
        if got != sample.sha256:
            raise InputError(sample.name, f"checksum mismatch: got sha256 {got}, expected "
                                          f"{sample.sha256}; the file was not kept")
        publish_mode(tmp)
        tmp.replace(target)
        return target, True
    finally:
        if tmp.exists():
            tmp.unlink()


def cmd_fetch(args: argparse.Namespace) -> int:
    folder = Path(args.output)
    mirror = Path(args.mirror) if args.mirror else None
    if folder.exists() and not folder.is_dir():
        raise InputError(folder, "-o is a file; give the folder the samples go into")
    if mirror is not None and not mirror.is_dir():
        raise InputError(mirror, "--from: no such folder" if not mirror.exists()
                         else "--from is a file; give the folder holding the samples")
    chosen = [s for s in SAMPLES if not args.only or s.name in args.only]
    made_folder = not folder.exists()
    try:
        for sample in chosen:
            print(f"{sample.name} ({sample.size / 1e6:.1f} MB) ...", end=" ", file=sys.stderr,
                  flush=True)
            path, fetched = fetch_sample(sample, folder, mirror, args.timeout,
                                         force=args.force)
            print("fetched, checksum ok" if fetched else "present, checksum ok", file=sys.stderr)
    except InputError:
        print("failed", file=sys.stderr)
        if made_folder and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()  # a failed first fetch leaves no empty folder behind
        raise
    print(f"{len(chosen)} sample(s) in {folder}")
    return 0


def cmd_list(args: argparse.Namespace) -> int:
    for sample in SAMPLES:
        print(f"{sample.name:24} {sample.size / 1e6:5.1f} MB  {sample.what}")
    return 0
