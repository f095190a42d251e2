"""Users Manager: registration, manager binding, Rep_i = total review / allocation count."""

from __future__ import annotations

import pytest
from medc_registry.chain import ContractRevert
from registry_helpers import revert_of

ONE = 10**18


@pytest.fixture
def solo(registry):
    """A second Users Manager whose manager is account 5 (an EOA), to call the manager-only functions."""
    chain = registry.chain
    umc = chain.contract("UsersManager", chain.deploy("UsersManager", sender=5).contract_address)
    chain.transact(umc.functions.setManager(chain.addresses[5]), sender=5)
    chain.transact(umc.functions.addUser(), sender=1)
    return chain, umc


def test_add_user_starts_at_half_reputation_and_emits_event(registry):
    result = registry.register_user()
    ev = registry.users.events.UserAdded().process_receipt(result.receipt)[0]["args"]
    assert ev["user"] == registry.address and ev["reputation"] == ONE // 2
    info = registry.user()
    assert (info.registered, info.reputation, info.alloc_count, info.total_review) == (True, 0.5, 0, 0.0)


def test_registering_twice_reverts(registry):
    registry.register_user()
    with pytest.raises(ContractRevert) as exc:
        registry.register_user()
    assert revert_of(exc).error == "AlreadyRegistered"
    assert "already registered" in str(exc.value)


def test_unregistered_reputation_read_reverts(registry):
    with pytest.raises(ContractRevert) as exc:
        registry.chain.call(registry.users.functions.reputationOf(registry.chain.addresses[7]))
    assert revert_of(exc).error == "UnregisteredUser"
    assert exc.value.values["user"] == registry.chain.addresses[7]


def test_only_the_models_manager_updates_users(registry, users):
    owner = users[0].address
    for fn in (
        registry.users.functions.updateInfo(owner, 1),
        registry.users.functions.updateReputation(owner, 1),
    ):
        with pytest.raises(ContractRevert) as exc:
            registry.chain.transact(fn, sender=1)
        assert revert_of(exc).error == "NotManager"


def test_manager_binding_is_admin_only_and_once(registry):
    chain = registry.chain
    umc = chain.contract("UsersManager", chain.deploy("UsersManager", sender=0).contract_address)
    with pytest.raises(ContractRevert) as exc:
        chain.transact(umc.functions.setManager(chain.addresses[1]), sender=1)
    assert revert_of(exc).error == "NotAdmin"
    with pytest.raises(ContractRevert) as exc:
        chain.transact(umc.functions.setManager("0x" + "00" * 20), sender=0)
    assert revert_of(exc).error == "ZeroAddress"
    chain.transact(umc.functions.setManager(chain.addresses[1]), sender=0)
    with pytest.raises(ContractRevert) as exc:
        chain.transact(umc.functions.setManager(chain.addresses[2]), sender=0)
    assert revert_of(exc).error == "ManagerAlreadySet"
    # The registry's own Users Manager is bound to its Models Manager.
    assert registry.chain.call(registry.users.functions.manager()) == registry.deployment.models


def test_reputation_is_total_review_over_allocation_count(solo):
    chain, umc = solo
    user = chain.addresses[1]
    chain.transact(umc.functions.updateInfo(user, 2), sender=5)
    chain.transact(umc.functions.updateReputation(user, ONE), sender=5)
    assert chain.call(umc.functions.getUser(user)) == [True, ONE // 2, 2, ONE]  # 1.0 / 2
    chain.transact(umc.functions.updateReputation(user, ONE // 4), sender=5)
    assert chain.call(umc.functions.reputationOf(user)) == (ONE + ONE // 4) // 2


def test_manager_calls_validate_their_input(solo):
    chain, umc = solo
    user, stranger = chain.addresses[1], chain.addresses[8]
    cases = [
        (umc.functions.updateInfo(user, 0), "ZeroCount"),
        (umc.functions.updateInfo(stranger, 1), "UnregisteredUser"),
        (umc.functions.updateReputation(user, ONE), "ReviewsExceedAllocations"),  # no allocation yet
    ]
    for fn, error in cases:
        with pytest.raises(ContractRevert) as exc:
            chain.transact(fn, sender=5)
        assert revert_of(exc).error == error
    chain.transact(umc.functions.updateInfo(user, 1), sender=5)
    with pytest.raises(ContractRevert) as exc:
        chain.transact(umc.functions.updateReputation(user, ONE + 1), sender=5)
    assert revert_of(exc).error == "ReviewOutOfRange"
