"""Wire formats and codecs. Nothing in this package does I/O."""
