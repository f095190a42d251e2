// SPDX-License-Identifier: Apache-2.0
pragma solidity 0.8.28;

/// @title What the MEDC contracts share
/// @notice The fixed-point constants and the errors that both the Users Manager and the Models
///         Manager use, declared once.

/// @notice The fixed-point constants of both contracts (1e18 = 1.0).
library Fixed {
    /// @notice Fixed-point one (1.0).
    uint256 internal constant ONE = 1e18;
    /// @notice Reputation of a new user and of a model not reviewed yet (0.5).
    uint256 internal constant INITIAL_REPUTATION = 5e17;
}

/// @notice `user` is not registered with the Users Manager.
error UnregisteredUser(address user);
/// @notice A review must be in [0, Fixed.ONE].
error ReviewOutOfRange(uint256 review);
