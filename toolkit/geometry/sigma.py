"""The relative 1-sigma tables one measurement uses: the defaults with the shipped networks' measured ones over them.

Imported by :mod:`.scale` and :mod:`.dbh` (through :mod:`.measure`); imports :mod:`.config` only.
"""
from __future__ import annotations

from dataclasses import dataclass

from .config import SigmaConfig
from .perception import Perception

__all__ = ["SigmaTables", "sigma_tables"]


@dataclass(frozen=True)
class SigmaTables:
    """Relative 1-sigma terms by scale source or estimator (fractions).

    Attributes
    ----------
    model : the exact-perception table (:attr:`~.config.SigmaConfig.model`); its ``ovality``,
        ``edge_px`` and ``cloud_extra`` apply to any perception.
    network : the network table (:attr:`~.config.SigmaConfig.model_network`) with the shipped
        networks' measured values (``Perception.sigma_network``) over it.
    net : whether the perception is the networks' (else ground truth).
    """
    model: dict
    network: dict
    net: bool

    @property
    def by_perception(self) -> dict:
        """The table of this perception's scale sources: ``network`` or ``model``."""
        return self.network if self.net else self.model


def sigma_tables(perc: Perception, config: SigmaConfig | None = None) -> SigmaTables:
    """The :class:`SigmaTables` for ``perc`` (network perception when ``perc.source`` is
    "network") from the default tables of ``config``."""
    cfg = config or SigmaConfig()
    return SigmaTables(model=cfg.model, network={**cfg.model_network, **(perc.sigma_network or {})},
                       net=perc.source == "network")
