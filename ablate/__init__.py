"""ablate: ablation studies of camera + LiDAR sensor-fusion networks."""

from collections.abc import Sequence

from omegaconf import OmegaConf

from ablate.hardware import register_resolvers

__version__ = "0.1.0"


def _channels(names: Sequence[str]) -> dict[str, int]:
    """Config resolver ``${channels:${modalities}}``: modality names -> {name: input channels}."""
    from ablate.data.dataset import MODALITIES

    unknown = [n for n in names if n not in MODALITIES]
    if unknown:
        raise ValueError(f"unknown modality {unknown[0]!r} in `modalities`; valid: {', '.join(MODALITIES)}")
    return {str(n): MODALITIES[n] for n in names}


def _docs() -> str:
    """Config resolver ``${ablate_docs:}``: the folder of the documentation installed with the package (a
    checkout's docs/), for the commands' --help."""
    from pathlib import Path

    return str(Path(__file__).resolve().parent / "docs")


OmegaConf.register_new_resolver("channels", _channels, replace=True)
OmegaConf.register_new_resolver("ablate_docs", _docs, replace=True)
register_resolvers()
