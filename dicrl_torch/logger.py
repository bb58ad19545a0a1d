"""One logger abstraction: namespaced scalar tags (``outer/``, ``inner/``, ``consensus/``,
``eval/``) and images, one TensorBoard run directory per learner plus ``network/`` for
quantities across learners (disagreement)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


class NullLogger:
    """Logs nothing (the default for library use and tests)."""

    def scalar(self, run: str, tag: str, value: float, step: int) -> None:
        pass

    def image(self, run: str, tag: str, image: np.ndarray, step: int) -> None:
        pass

    def has_run(self, run: str) -> bool:
        """Whether ``run`` already holds logged values (from this or an earlier process)."""
        return False

    def close(self) -> None:
        pass


class TensorBoardLogger(NullLogger):
    """TensorBoard event files under ``root/<run>/``; ``run`` is ``learner<v>``,
    ``c_icrl`` or ``network``.

    Args:
        root: directory of the runs (e.g. the Hydra run directory + ``/tb``).
    """

    def __init__(self, root: str | Path) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self._writer_cls = SummaryWriter
        self.root = Path(root)
        self._writers: dict[str, object] = {}

    def _writer(self, run: str):
        if run not in self._writers:
            self._writers[run] = self._writer_cls(log_dir=str(self.root / run))
        return self._writers[run]

    def scalar(self, run: str, tag: str, value: float, step: int) -> None:
        self._writer(run).add_scalar(tag, float(value), step)

    def image(self, run: str, tag: str, image: np.ndarray, step: int) -> None:
        """``image`` ``[H, W, 3]`` uint8."""
        self._writer(run).add_image(tag, image, step, dataformats="HWC")

    def has_run(self, run: str) -> bool:
        return run in self._writers or any((self.root / run).glob("events.out.tfevents.*"))

    def close(self) -> None:
        for w in self._writers.values():
            w.close()
        self._writers.clear()
