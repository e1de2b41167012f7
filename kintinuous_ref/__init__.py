"""kintinuous_ref: the readable NumPy specification of extended Kintinuous (Whelan et al. 2013).

One algorithm per module, named as in the paper, with its equation numbers in comments.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("kintinuous")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+source"
