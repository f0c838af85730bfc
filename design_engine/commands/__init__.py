"""The engine's commands (`metarig simulate|modes|design|pareto|robustness|export|bench`):
leaves that parse arguments, call the libraries and print; only `metarig.cli` imports them."""
