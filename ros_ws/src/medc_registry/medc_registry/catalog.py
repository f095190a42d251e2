"""The shared models as the Models Manager records them: each model's record, read back through one
chain client, the feature names an application's first model fixed, and the description a new model
is recorded with (its feature names and its bundle's summary), checked before it is shared."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from medc_training.qos import from_fixed

from .chain import ChainClient, ContractRevert
from .ranker import models_list
from .records import SharedModel, description_features

#: Longest model description recorded on chain (UTF-8 bytes of the JSON :func:`model_description`
#: writes; a shared bundle's is a few hundred). Storage costs gas per 32 bytes: 4 KB is ~3 M gas.
MAX_DESCRIPTION_BYTES = 4096


class ModelCatalog:
    """The models of one Models Manager contract (``models``, over ``chain``), read with calls only.

    An application's feature names are fixed by its first model and never change, so they are
    read once and kept; registries acting as other accounts share one catalog.
    """

    def __init__(self, chain: ChainClient, models: Any) -> None:
        self.chain = chain
        self.models = models
        self._feature_names: dict[str, tuple[str, ...]] = {}

    def model(self, model_id: int) -> SharedModel:
        """Model ``model_id`` (ContractRevert ``UnknownModel`` if there is none)."""
        owner, app_id, env, price, rep, count, total = self.chain.call(
            self.models.functions.getModel(model_id)
        )
        cid, description = self.chain.call(self.models.functions.getModelText(model_id))
        application = self.chain.call(self.models.functions.applicationName(app_id))
        return SharedModel(
            model_id,
            owner,
            application,
            cid,
            description,
            description_features(description),
            tuple(env),
            price,
            from_fixed(rep),
            count,
            from_fixed(total),
        )

    def count(self) -> int:
        """Number of shared models."""
        return self.chain.call(self.models.functions.modelCount())

    def list_models(self, application: str | None = None) -> list[SharedModel]:
        """All shared models (of ``application`` when given)."""
        out = [self.model(i) for i in range(self.count())]
        return [m for m in out if application is None or m.application == application]

    def feature_names(self, application: str) -> tuple[str, ...] | None:
        """Feature names of ``application`` (fixed by its first model; () when it named none),
        None when no model of it was shared."""
        if application in self._feature_names:
            return self._feature_names[application]
        try:
            first = models_list(self.chain, self.models, application)[0]
        except ContractRevert as exc:
            if exc.error != "UnknownApplication":
                raise
            return None
        _cid, description = self.chain.call(self.models.functions.getModelText(first))
        self._feature_names[application] = description_features(description)
        return self._feature_names[application]

    def new_description(self, application: str, names: tuple[str, ...], bundle: bytes,
                        description: str | Mapping[str, Any] | None) -> str:
        """The description a new model of ``application`` with feature ``names`` is recorded with
        (:func:`model_description`). Raises ValueError when the names are not the application's
        or the description is over MAX_DESCRIPTION_BYTES."""
        existing = self.feature_names(application)
        if existing is not None and names and existing and names != existing:
            raise ValueError(f"{application!r} models use features {list(existing)}, got {list(names)}")
        text = model_description(names, bundle, description)
        if len(text.encode("utf-8")) > MAX_DESCRIPTION_BYTES:
            raise ValueError(f"the model's description would be {len(text.encode('utf-8'))} bytes, over "
                             f"the {MAX_DESCRIPTION_BYTES} byte limit: shorten the description")
        return text


def bundle_summary(data: bytes) -> dict[str, Any]:
    """What a requester must know before using a shared policy bundle, read from its validated
    manifest (the weights are never decoded): the observation variant it takes and its
    architecture. {} for bytes that are not a policy bundle (the registry stores any file)."""
    from medc_training.bundle import BundleError, manifest_observation, read_manifest
    from medc_training.envs import application

    try:
        manifest = read_manifest(data)
    except BundleError:
        return {}
    out: dict[str, Any] = {"architecture": manifest["architecture"].get("name", "?")}
    if application(manifest["application"]).manifest_names_view:
        out["observation"] = manifest_observation(manifest)
    return out


def model_description(
    names: tuple[str, ...], bundle: bytes, description: str | Mapping[str, Any] | None
) -> str:
    """The description a shared model is recorded with: compact JSON of its feature names, the
    bundle's summary (:func:`bundle_summary`) and the sharer's ``description`` ("" if empty)."""
    desc: dict[str, Any] = {}
    if names:
        desc["features"] = list(names)
    desc.update(bundle_summary(bundle))
    if isinstance(description, Mapping):
        desc.update(description)
    elif description:
        desc["text"] = str(description)
    return json.dumps(desc, separators=(",", ":"), sort_keys=True) if desc else ""
