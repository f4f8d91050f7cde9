"""What a loaded domain holds in memory: the one model both the preflight's ``--memory-limit``
plan (``vastray.preflight``) and the cache's resident-bytes figure (``DomainBVH.nbytes``) use.

A domain loaded with the compiled binding holds its arrays as read from the store (Embree
uses the vertex and index arrays in place) plus Embree's own memory: the BVH, the triangle
blocks its leaves store, and the padded copies ``embree.scenes`` makes, per triangle, and a
small fixed part per scene. While the BVH is built, Embree's builder holds temporaries on top
of that, which it frees when the build ends.

Measured as RSS (VmRSS, and VmHWM for the build's peak, reset before each build) on this
project's 2-core machine, Embree 4.4 (embreex 4.4 wheel), 2026-11-29, one process building
domains one after another:

- the 100 M-triangle ``rm`` store of README's "Larger than memory" (domains of 0.7-2.1 M
  triangles): resident 58-72 B per triangle beyond the arrays (20 B per triangle), LOW and
  MEDIUM build quality alike; the build's peak 100-104 B per triangle beyond them;
- a 972,338-triangle ``rm`` isosurface (one domain): 69 resident, 101 at the build's peak;
- 40 domains of about 1,200 triangles (``rm`` 128^3 in 16x8x8): 130 B per triangle in all,
  i.e. about 70 KiB per scene beyond 70 B per triangle.

The fast BVH (``--bvh fast``, ``scene.bvh_choice``: Embree's Morton builder over Embree's
compact triangle layout) holds less: 51 B per triangle beyond the arrays on a 403,202-triangle
height field, 50-52 on four domains of 0.2-0.7 M triangles of the ``rm`` 1600^3 store and
50-53 on three of 0.6-1.1 M of the 100 M-triangle store, its build's peak 8 B a triangle
above that (2026-12-05). The Morton builder without the compact layout held 90-92 B a
triangle (peak 98-100): the layout's leaves index the vertex buffer instead of copying the
vertices.

The figures below sit above every one of those. Without the compiled binding (the embreex
fallback, which copies the mesh into Embree's buffers) the older, larger per-triangle figure
is kept: it was never measured there.
"""

from __future__ import annotations

#: Bytes per triangle a built domain holds beyond its arrays (compiled binding).
BVH_BYTES_PER_TRIANGLE = 76

#: The same for the fast BVH (Embree's Morton builder, compact layout).
FAST_BVH_BYTES_PER_TRIANGLE = 60

#: The same for the embreex fallback: Embree's copy of the mesh (36 + 12 B) and the BVH (64 B).
FALLBACK_BVH_BYTES_PER_TRIANGLE = 36 + 12 + 64

#: Bytes each loaded domain's Embree scene holds whatever its size.
SCENE_FIXED_BYTES = 128 * 1024

#: Bytes per triangle Embree's builder holds only while it builds (peak less resident).
BUILD_BYTES_PER_TRIANGLE = 40

#: Domains a process may build at once: its preloader's and a render worker's demand load.
CONCURRENT_BUILDS = 2


def resident_bytes(n_triangles: int, array_bytes: int, compiled: bool = True,
                   fast: bool = False) -> int:
    """Bytes one loaded domain holds: its arrays (``array_bytes``) and Embree's scene (the
    fast BVH's with ``fast``; the embreex fallback ignores it)."""
    per_triangle = (FALLBACK_BVH_BYTES_PER_TRIANGLE if not compiled
                    else FAST_BVH_BYTES_PER_TRIANGLE if fast else BVH_BYTES_PER_TRIANGLE)
    return int(array_bytes) + int(n_triangles) * per_triangle + SCENE_FIXED_BYTES


def build_bytes(largest_triangles: int) -> int:
    """Bytes the builds in progress add at their peak: ``CONCURRENT_BUILDS`` builds of the
    largest domain (``largest_triangles`` triangles)."""
    return CONCURRENT_BUILDS * BUILD_BYTES_PER_TRIANGLE * int(largest_triangles)


def domain_footprints(domains, fast: bool = False) -> list[int]:
    """Bytes each domain holds once loaded: its arrays plus Embree's scene
    (``resident_bytes``; ``fast``: the fast BVH's, ``--bvh``), as the preflight plans them
    and a cache bounded by bytes charges them."""
    from vastray.scene.embree.library import binding

    compiled = binding() is not None
    return [resident_bytes(d.n_triangles, d.nbytes, compiled, fast) for d in domains]
