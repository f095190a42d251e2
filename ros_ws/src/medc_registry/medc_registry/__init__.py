"""medc_registry: the MEDC model registry (smart contracts, chain client, IPFS content store).

Public API::

    from medc_registry import Registry, ChainClient, LocalContentStore, KuboContentStore, compute_cid
"""

from .chain import ChainClient, ChainError, ContractRevert
from .cid import ContentMismatchError, compute_cid, verify
from .content import (
    ContentIntegrityError,
    ContentNotFoundError,
    ContentStoreError,
    KuboContentStore,
    LocalContentStore,
)
from .registry import Allocation, Deployment, Registry, SharedModel, UserInfo, deploy_contracts

__all__ = [
    "Allocation",
    "ChainClient",
    "ChainError",
    "ContentIntegrityError",
    "ContentMismatchError",
    "ContentNotFoundError",
    "ContentStoreError",
    "ContractRevert",
    "Deployment",
    "KuboContentStore",
    "LocalContentStore",
    "Registry",
    "SharedModel",
    "UserInfo",
    "compute_cid",
    "deploy_contracts",
    "verify",
]
