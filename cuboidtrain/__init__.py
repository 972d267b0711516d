"""cuboid-fit's trainer and fitting library (the consumer half of cuboid-fit).

The Python API:

    from cuboidtrain import Fitter, FitOptions
    fit = Fitter.from_shipped().fit("mask.png")

`Fitter`, `Fit` and `FitOptions` are imported on first use, so that `import cuboidtrain`
(and the command line's --help) does not wait for torch.
"""
from __future__ import annotations

_API = {"Fitter": "cuboidtrain.fit.fitter", "Fit": "cuboidtrain.fit.fitter", "FitOptions": "cuboidtrain.fit.options"}
__all__ = list(_API)


def __getattr__(name: str):
    if name in _API:
        import importlib

        return getattr(importlib.import_module(_API[name]), name)
    raise AttributeError(f"module 'cuboidtrain' has no attribute {name!r}")
