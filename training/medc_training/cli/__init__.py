"""Command-line entry points of medc_training (medc-train, medc-inspect, medc-clone, medc-bench train).

Each module exposes ``main(argv: list[str] | None = None) -> int`` and is wired as a console script
in training/pyproject.toml.
"""
