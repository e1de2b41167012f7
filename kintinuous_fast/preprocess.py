"""kintinuous_ref.preprocess's public names from the "auto" backend: kintinuous_fast.cuda.preprocess
where a GPU works, else kintinuous_fast.cpu.preprocess (see kintinuous_fast.select_backend)."""

from kintinuous_fast import select_backend as _select_backend

_implementation = _select_backend("auto").preprocess
globals().update({name: getattr(_implementation, name) for name in _implementation.__all__})
__all__ = list(_implementation.__all__)
