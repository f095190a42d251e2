"""Hostile inputs against the registry, second round (issue 20, items 5 and 9-13): JSON from the
graph and the chain, hostile JSON-RPC and IPFS nodes, other users' on-chain strings and the CLI's
own arguments and files. Every hostile message, server and file is built here; the tests are fast
(loopback servers, the embedded chain, subprocesses of a few seconds)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest


# ----------------------------------------------------------------------------- item 5: deep JSON
def _run(code: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          timeout=timeout)


def test_bridge_refuses_json_nested_70000_deep_even_with_a_raised_recursion_limit(tmp_path):
    """What crashed medc-bridge (exit 139): requirements_json / weights_json nested 70,000 deep in
    a process whose recursion limit the embedded chain raised to 100,000. Run in a child process,
    so a crash shows as its exit status instead of killing the test run."""
    proc = _run(f"""
        import sys
        from medc_registry.bridge_node import BridgeError, RegistryBridge
        from medc_registry.records import description_features
        sys.setrecursionlimit(100_000)  # what py-evm does in the bridge's process
        deep = "[" * 70_000 + "]" * 70_000
        deep_object = '{{"a":' * 70_000 + "1" + "}}" * 70_000
        shallow_deep = "[" * 2000 + "]" * 2000  # within the size limit: the depth scan refuses it

        class Registry:  # never reached: the JSON is refused first
            def request_models(self, *a, **k):
                raise AssertionError("a refused request reached the registry")

        bridge = RegistryBridge(Registry(), {str(tmp_path / "cache")!r})
        for text in (deep, deep_object, shallow_deep):
            for args in ((text, ""), ('{{"agents": 3}}', text)):
                try:
                    bridge.request("target_localization", *args)
                except BridgeError as exc:
                    assert "nests deeper than 16 levels" in str(exc) or "character limit" in str(exc), exc
                    assert text is not shallow_deep or "nests deeper" in str(exc), exc
                else:
                    raise AssertionError("accepted")
            # The same text as an on-chain model description names no features, and never crashes.
            assert description_features(text) == ()
        print("refused")
    """)
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
    assert proc.stdout.strip() == "refused"


def test_graph_json_limits_and_a_valid_request_still_parses(tmp_path):
    from medc_registry.bridge_node import BridgeError, RegistryBridge
    from medc_registry.records import description_features

    class Registry:
        def request_models(self, application, requirements, weights, **kw):
            self.seen = (requirements, weights)
            return []

    reg = Registry()
    bridge = RegistryBridge(reg, tmp_path / "cache")
    bridge.request("target_localization", '{"agents": 3, "walls": 2}', '{"agents": 0.5, "walls": 0.5}')
    assert reg.seen == ({"agents": 3, "walls": 2}, {"agents": 0.5, "walls": 0.5})
    for bad, why in (
        ('{"agents": 3, "agents": 4}', "twice"),
        ('{"agents": NaN}', "NaN"),
        ('{"agents": 1' + "0" * 100 + "}", "more than 40 characters"),
        ('{"a": "' + "x" * 5000 + '"}', "character limit"),
        ('{"\\ud800": 1}', "lone surrogate"),
        ("[1, 2]", "must be a JSON object"),
    ):
        with pytest.raises(BridgeError, match=why):
            bridge.request("target_localization", bad)
    assert description_features('{"features": ["agents", "walls"]}') == ("agents", "walls")
    assert description_features('{"features": [1, 2]}') == ()
    assert description_features('{"features": "agents"}') == ()
