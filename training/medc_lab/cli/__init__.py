"""Entry points of the research harness (medc-reproduce and the studies' ``python -m`` commands).

Each module exposes ``main(argv: list[str] | None = None) -> int``.
"""
