"""The package version, in its own module so low layers (io, manifests) can read it without the package root."""

__version__ = "0.1.0"
