"""File formats at the edges: meshes, PDS4 products, SPICE kernels."""
