"""``Film.add_partial``: a node folds in only the rows of its partial paths that change the
film, and the film is the same, bit for bit, as folding in every row."""

from __future__ import annotations

import numpy as np

from vastray.render import film as film_module
from vastray.render.film import Film, changing_rows
from vastray.render.integrators import PathResult

WIDTH, HEIGHT = 24, 16


def partial_paths(seed: int = 0, n: int = 2000) -> tuple[np.ndarray, np.ndarray, PathResult]:
    """A tile's pixel and sample keys (n,) and its paths, most of them traced elsewhere: zero
    radiance (some -0.0), inf distances and zero normals; a few with radiance, first hits, a
    NaN radiance, a NaN distance, and a normal without a distance."""
    rng = np.random.default_rng(seed)
    keys = rng.permutation(WIDTH * HEIGHT * 8)[:n]  # a tile's paths: distinct (pixel, sample)
    pixel = (keys % (WIDTH * HEIGHT)).astype(np.uint32)
    sample = (keys // (WIDTH * HEIGHT)).astype(np.uint32)
    paths = PathResult.empty(n)
    traced = rng.random(n) < 0.1
    paths.radiance[traced] = rng.random((traced.sum(), 3))
    paths.radiance[rng.random(n) < 0.05] = -0.0
    hit = traced & (rng.random(n) < 0.5)
    paths.first_t[hit] = rng.random(hit.sum()).astype(np.float32)
    paths.first_normal[hit] = rng.random((hit.sum(), 3)).astype(np.float32)
    untouched = np.flatnonzero(~traced)
    paths.radiance[untouched[0], 1] = np.nan
    at_zero = untouched[sample[untouched] == 0]
    paths.first_t[at_zero[0]] = np.nan
    paths.first_normal[at_zero[1]] = (0.0, 0.0, 1.0)
    return pixel, sample, paths


def fold_every_row(film: Film, pixel, sample, paths: PathResult) -> None:
    """``add_partial`` as it was: every row folded in."""
    film.add(pixel, paths.radiance, counted=np.zeros(len(pixel), bool), sample=sample)
    zero = np.nonzero(sample == 0)[0]
    np.minimum.at(film.depth, pixel[zero], paths.first_t[zero])
    film.normal[pixel[zero]] += paths.first_normal[zero]


def layers(film: Film) -> list[bytes]:
    return [a.tobytes() for a in (film.sum, film.batch, film.count, film.depth, film.normal)]


def test_folding_the_changing_rows_gives_the_film_of_every_row_bit_for_bit():
    every, changing = Film(WIDTH, HEIGHT), Film(WIDTH, HEIGHT)
    for seed in range(4):  # several tiles into one film, as a node's frame
        pixel, sample, paths = partial_paths(seed)
        with np.errstate(invalid="ignore"):  # the NaN distance
            fold_every_row(every, pixel, sample, paths)
            changing.add_partial(pixel, sample, paths)
    assert layers(changing) == layers(every)
    assert np.isnan(changing.sum).any() and np.isnan(changing.depth).any()  # both cases ran


def test_only_the_rows_that_change_the_film_reach_its_kernel(monkeypatch):
    pixel, sample, paths = partial_paths()
    rows = changing_rows(sample, paths)
    expected = (np.any(paths.radiance != 0, axis=1)
                | ((sample == 0) & ((paths.first_t != np.inf)
                                    | np.any(paths.first_normal != 0, axis=1))))
    assert np.array_equal(rows, np.flatnonzero(expected))
    assert 0 < len(rows) < len(pixel) / 5  # most rows were traced elsewhere
    seen = []
    kernel = film_module.kernels.film_add
    monkeypatch.setattr(film_module.kernels, "film_add",
                        lambda *args: (seen.append(len(args[3])), kernel(*args)))
    with np.errstate(invalid="ignore"):
        Film(WIDTH, HEIGHT).add_partial(pixel, sample, paths)
    assert seen == [len(rows)]
