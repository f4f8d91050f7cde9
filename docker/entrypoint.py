"""The vastray image's entrypoint: hand the folders the command writes to its user, drop root,
run ``vastray ARGS``.

Docker creates a fresh named volume (``/keys``) and a missing bind-mount source
(``docker/data/out``) owned by root, so a container that starts as an unprivileged user
cannot write them. The image therefore starts as root, and this script:

1. picks the user to run as: the owner of ``$VASTRAY_OWNER_FROM`` (default ``/data``, the
   bind-mounted data folder, so the images land on the host owned by whoever owns
   ``docker/data``), or the image's ``vastray`` user (uid 1000) when that is root-owned or
   missing;
2. creates each folder of ``$VASTRAY_WRITABLE`` (``:``-separated) and gives it, and what is in
   it, to that user;
3. runs ``vastray`` with its arguments as that user, with no supplementary groups and a
   ``HOME`` it can write, through ``setpriv`` (util-linux, in every Debian image).

Started as a non-root user (``docker run --user``), it changes nothing and only checks that
the folders of ``$VASTRAY_WRITABLE`` are writable, failing with one line naming the folder
that is not, rather than leaving ``vastray`` to fail halfway with a traceback.

Written in Python rather than shell for its checks and one-line errors; ``setpriv`` drops
root (``gosu``'s job, without installing ``gosu``).
"""

from __future__ import annotations

import os
import pwd
import shutil
import sys

#: The image's user (``useradd --uid 1000 vastray`` in the Dockerfile).
DEFAULT_UID = DEFAULT_GID = 1000
PROG = "vastray-entrypoint"


class EntrypointError(Exception):
    """A problem the user can fix, reported as one line."""


def run_as(owner_from: str) -> tuple[int, int]:
    """The uid and gid to run as: ``owner_from``'s owner, or 1000:1000 when it is root-owned
    or missing."""
    try:
        st = os.stat(owner_from)
    except OSError:
        return DEFAULT_UID, DEFAULT_GID
    if st.st_uid == 0:
        return DEFAULT_UID, DEFAULT_GID
    return st.st_uid, st.st_gid


def hand_over(folder: str, uid: int, gid: int) -> None:
    """Create ``folder`` (and its parents) and give it and everything in it to ``uid:gid``
    (symbolic links themselves, never what they point to)."""
    try:
        os.makedirs(folder, exist_ok=True)
        for top, dirs, files in os.walk(folder):
            for name in [top, *(os.path.join(top, n) for n in dirs + files)]:
                st = os.lstat(name)
                if (st.st_uid, st.st_gid) != (uid, gid):
                    os.lchown(name, uid, gid)
    except OSError as exc:
        raise EntrypointError(f"{folder}: cannot hand it to uid {uid}: "
                              f"{exc.strerror or exc}") from None


def check_writable(folder: str) -> None:
    """Refuse, as a non-root user, a folder that is not there (and cannot be made) or not
    writable."""
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        raise EntrypointError(f"{folder}: cannot create it as uid {os.getuid()}: "
                              f"{exc.strerror or exc}; start the container as root (the "
                              f"image's default) so it is handed to its user") from None
    if not os.access(folder, os.W_OK | os.X_OK):
        raise EntrypointError(f"{folder}: not writable by uid {os.getuid()} (owned by uid "
                              f"{os.stat(folder).st_uid}); start the container as root (the "
                              f"image's default) so it is handed to its user, or chown it")


def home_for(uid: int) -> str:
    """A ``HOME`` that ``uid`` can write (numba keeps its compiled kernels under it, and fails
    without one): its passwd home when it owns it, else ``/tmp``."""
    try:
        home = pwd.getpwuid(uid).pw_dir
        if os.stat(home).st_uid == uid:
            return home
    except (KeyError, OSError):  # a host uid the image does not know
        pass
    return "/tmp"


def main(argv: list[str]) -> int:
    writable = [f for f in os.environ.get("VASTRAY_WRITABLE", "").split(":") if f]
    command = ["vastray", *argv]
    try:
        if os.geteuid() == 0:
            uid, gid = run_as(os.environ.get("VASTRAY_OWNER_FROM", "/data"))
            for folder in writable:
                hand_over(folder, uid, gid)
            if shutil.which("setpriv") is None:
                raise EntrypointError("setpriv (util-linux) is missing from the image: cannot "
                                      "drop root")
            os.environ["HOME"] = home_for(uid)
            command = ["setpriv", f"--reuid={uid}", f"--regid={gid}", "--clear-groups",
                       "vastray", *argv]
        else:
            for folder in writable:
                check_writable(folder)
            if not os.access(os.environ.get("HOME", "/"), os.W_OK):
                os.environ["HOME"] = home_for(os.getuid())
        os.execvp(command[0], command)
    except EntrypointError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:  # execvp: vastray not installed
        print(f"{PROG}: error: cannot run {command[0]}: {exc.strerror or exc}", file=sys.stderr)
        return 127
    return 0  # not reached: execvp replaces this process


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
