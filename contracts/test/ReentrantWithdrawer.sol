// SPDX-License-Identifier: Apache-2.0
pragma solidity 0.8.28;

import {ModelsManager} from "../src/ModelsManager.sol";
import {UsersManager} from "../src/UsersManager.sol";

/// @title Test-only attacker: a model owner whose receive() re-enters withdraw().
/// @notice Used by tests/registry to show the payout cannot be taken twice.
contract ReentrantWithdrawer {
    ModelsManager public immutable target;
    UsersManager public immutable users;
    /// @notice Whether the nested withdraw() call succeeded (it must not).
    bool public reentrySucceeded;
    /// @notice Revert data of the nested withdraw() call.
    bytes public reentryError;
    /// @notice Number of times receive() ran.
    uint256 public receiveCount;

    constructor(ModelsManager target_, UsersManager users_) {
        target = target_;
        users = users_;
    }

    /// @notice Register this contract as a user.
    function register() external {
        users.addUser();
    }

    /// @notice Share a model as this contract.
    /// @param application Application name.
    /// @param cid CID string.
    /// @param envDetails Environment features.
    /// @param price Price in wei.
    function share(string calldata application, string calldata cid, uint32[] calldata envDetails, uint256 price)
        external
    {
        target.addModel(application, cid, "", envDetails, price);
    }

    /// @notice Withdraw what this contract is owed; receive() tries to withdraw again.
    function attack() external {
        target.withdraw();
    }

    receive() external payable {
        receiveCount += 1;
        if (receiveCount == 1) {
            (bool ok, bytes memory err) = address(target).call(abi.encodeCall(ModelsManager.withdraw, ()));
            reentrySucceeded = ok;
            reentryError = err;
        }
    }
}
