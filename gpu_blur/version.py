"""The package's version.

Apart from ``gpu_blur/__init__.py``, so that a module records it without importing the
package's public API.
"""

__all__ = ["__version__"]

__version__ = "0.1.0"
