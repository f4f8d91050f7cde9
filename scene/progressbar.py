"""The progress bar every long step shows: ``tqdm``, made safe against a Ctrl-C that arrives
while a bar is being made (here, in the lowest layer, so that every layer can use it)."""

from __future__ import annotations

from tqdm import tqdm


class Bar(tqdm):
    """``tqdm`` that a Ctrl-C arriving while it is made leaves silent: tqdm's ``__init__``
    sets ``disable`` before ``pos``, so a bar interrupted in between printed an
    ``AttributeError`` traceback from its ``__del__`` on the way out of an interrupted
    command (seen on an animation interrupted at its first frame)."""

    def close(self) -> None:
        if not hasattr(self, "pos"):  # never finished its __init__: nothing shown, nothing held
            self.disable = True
            return
        super().close()
