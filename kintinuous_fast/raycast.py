"""kintinuous_ref.raycast's public names from the "auto" backend: kintinuous_fast.cuda.raycast
where a GPU works, else kintinuous_fast.cpu.raycast (see kintinuous_fast.select_backend)."""

from kintinuous_fast import select_backend as _select_backend

_implementation = _select_backend("auto").raycast
globals().update({name: getattr(_implementation, name) for name in _implementation.__all__})
__all__ = list(_implementation.__all__)
