"""The physics: lattice and geometry, material and material files, energy and its laws,
dynamics, statics, modal analysis, loading, regions and the preset scenes."""
