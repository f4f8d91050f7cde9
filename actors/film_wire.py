"""Films as wire messages (partial films combine with ``Film.merge``)."""

from __future__ import annotations

import numpy as np

from vastray.actors.protocol import FILM_FIELDS
from vastray.render.film import Film
from vastray.transport.codec import FRAME_LIMIT, Message, encode


def film_frames(film: Film, meta: dict | None = None, frame_limit: int = FRAME_LIMIT) -> list:
    """A film's message (``frame_limit``: ``PEER_FRAME_LIMIT`` for a film to a peer)."""
    return encode("film", {f: getattr(film, f) for f in FILM_FIELDS}, meta, frame_limit)


def film_from(message: Message, width: int, height: int) -> Film:
    """A writable Film from a decoded message (checks the pixel count)."""
    film = Film(width, height)
    for name in FILM_FIELDS:
        array = message.arrays[name]
        if array.shape != getattr(film, name).shape:
            raise ValueError(f"film field {name} has shape {array.shape}, expected "
                             f"{getattr(film, name).shape}")
        # a field that came in several frames was joined into a fresh, writable array by the
        # codec: taken as it is; one viewing a received frame (read-only) is copied
        setattr(film, name, array if array.flags.writeable else np.array(array))
    return film
