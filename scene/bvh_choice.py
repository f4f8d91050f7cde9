"""Which BVH Embree builds for a render's domains: the one that traces fastest, or the one
that builds fastest and holds least.

Embree's default build (SAH, ``RTC_BUILD_QUALITY_MEDIUM``) gives the BVH that traces fastest;
the fast BVH is Embree's Morton builder (the mesh's build quality ``LOW``) over Embree's
compact triangle layout (``RTC_SCENE_FLAG_COMPACT``: leaves index the vertex buffer instead
of holding copies of the vertices). The builder builds the same domain about 3x faster and
traces 5-30 % slower (28 % on random rays, about 5 % in ``bench/ooc.py --large``'s renders);
the layout holds 50-53 B a triangle beyond the store's arrays where the copied vertices held
90-92 (``scene.footprint``), so a memory budget caches 1.6x the domains, and each build
touches less fresh memory, at 20-30 % slower queries: on ``--large``'s store, CLI renders in
fresh processes took 16 % less time at a 25 % cache and 44 % less all cached (no gain showed
in ``bench/ooc.py``'s long-lived process), while the 100 M store's 1 M-path spec-ooc render,
whose queries weigh more, took about as long in its budget (bench/README, session 62).
Which wins depends on how many rays each loaded triangle serves: a large store is rendered
out of core, where a domain is loaded again after every eviction (2.7 loads a domain at a
25 % cache in ``bench/ooc.py --large``) and each repeated load serves a few dozen rays, so its
builds, not its traces, are the render's time.

The BVHs do not find the same hit for every ray: where a ray passes within float rounding
of a vertex, Embree may report another of the triangles around it (the builders differ for 6
rays in 50,000 aimed at vertices, ``tests/test_build_quality.py``; the layouts, whose
triangle tests round differently, for 0-2). So the choice is made from the store alone,
never from the cache, the node count or the scheduler: a render's image is the same bit for
bit whatever the cache holds and however many nodes share the work, and the single-process
reference renders with the same BVH.

- ``auto`` (default): ``fast`` for stores of at least :data:`FAST_TRIANGLES` triangles (the
  data vastray exists for: larger than memory, loaded more than once), ``quality`` below.
- ``fast``: Embree's Morton builder and compact layout for every domain, each domain attached
  as pieces of ``kernels.PIECE_TRIANGLES`` triangles (in pieces a domain builds in about half
  the time for a third less CPU, mostly by reusing heap pages earlier builds freed,
  ``scenes.Scene``, ``scene.heap``).
- ``quality``: Embree's default build (a cache smaller than the store builds the two-level
  form of the same BVH, ``scene.cache``: the same hits, 10-25 % faster to build).
"""

from __future__ import annotations

#: The values of ``--bvh``.
CHOICES = ("auto", "fast", "quality")
#: Stores of at least this many triangles build the fast BVH under ``auto``.
FAST_TRIANGLES = 8_000_000


def resolve(choice: str, n_triangles: int) -> str:
    """The BVH (``"fast"`` or ``"quality"``) a render whose ``--bvh`` is ``choice`` builds for a
    store of ``n_triangles`` triangles.

    Raises
    ------
    ValueError
        ``choice`` is not one of :data:`CHOICES`.
    """
    if choice not in CHOICES:
        raise ValueError(f"--bvh must be one of {', '.join(CHOICES)}, not {choice!r}")
    if choice == "auto":
        return "fast" if n_triangles >= FAST_TRIANGLES else "quality"
    return choice


def fast_builds(choice: str, n_triangles: int) -> bool:
    """Whether ``resolve(choice, n_triangles)`` is the fast (Morton) BVH."""
    return resolve(choice, n_triangles) == "fast"


def describe(choice: str, n_triangles: int) -> str:
    """The BVH a render builds, in words, for its report (e.g. ``fast (auto: 30.3 M
    triangles)``)."""
    name = resolve(choice, n_triangles)
    count = f"{n_triangles / 1e6:.1f} M" if n_triangles >= 1_000_000 else f"{n_triangles:,}"
    return f"{name} (auto: {count} triangles)" if choice == "auto" else name
