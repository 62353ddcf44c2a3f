"""The docs site's generated pages (``make docs``, ``mkdocs.yml``): references built from the
code at build time, so they cannot drift from it, and the pictures drawn from the cell's data.

It sits beside ``cli/`` at the top of the layers: it may read every part of scancell, and
nothing imports it.
"""
