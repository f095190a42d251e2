"""Command-line entry points of the product: medc-train, medc-inspect, medc-clone, medc-controllers
(:mod:`.play_controllers`), medc-bench train, and the ``python -m`` commands :mod:`.play_bundle`,
:mod:`.declaration_accuracy` and :mod:`.render`.

Each module exposes ``main(argv: list[str] | None = None) -> int``; the console scripts are wired in
training/pyproject.toml. The research harness has its own (:mod:`medc_lab.cli`).
"""
