// SPDX-License-Identifier: Apache-2.0
pragma solidity 0.8.28;

import {Fixed, ReviewOutOfRange, UnregisteredUser} from "./MedcShared.sol";

/// @title Users Manager Contract (UMC)
/// @notice Registers MEDC users and keeps their reputation (paper Table I):
///         Rep_i = Total Review / Models Alloc. Count, fixed point with 1e18 = 1.0, initial 0.5.
/// @dev Allocation counts and reviews are written only by the bound manager (the Models Manager
///      Contract), which enforces who may review what; this contract enforces the arithmetic.
contract UsersManager {
    /// @notice Fixed-point one (1.0), kept as a getter of this contract's interface.
    uint256 public constant ONE = Fixed.ONE;
    /// @notice Reputation of a user whose models have not been reviewed yet (0.5), kept as a getter.
    uint256 public constant INITIAL_REPUTATION = Fixed.INITIAL_REPUTATION;

    /// @dev One storage slot per user: 1 + 8 + 8 + 12 bytes.
    struct User {
        bool registered;
        uint64 reputation;
        uint64 allocCount;
        uint96 totalReview;
    }

    /// @notice Deployer; the only account that may bind the manager, once.
    address public immutable admin;
    /// @notice The contract allowed to call updateInfo and updateReputation.
    address public manager;

    mapping(address => User) private _users;

    error AlreadyRegistered(address user);
    error NotAdmin(address caller);
    error NotManager(address caller);
    error ManagerAlreadySet(address manager);
    error ZeroAddress();
    error ZeroCount();
    error ReviewsExceedAllocations(address user);

    event UserAdded(address indexed user, uint256 reputation);
    event ManagerSet(address indexed manager);
    event UserInfoUpdated(address indexed user, uint256 modelsAllocated, uint256 allocCount);
    event UserReputationUpdated(address indexed user, uint256 review, uint256 totalReview, uint256 reputation);

    modifier onlyManager() {
        if (msg.sender != manager) revert NotManager(msg.sender);
        _;
    }

    constructor() {
        admin = msg.sender;
    }

    /// @notice Bind the contract (normally the Models Manager) that reports allocations and reviews.
    /// @dev Callable once, by the deployer.
    /// @param manager_ Address of the manager contract.
    function setManager(address manager_) external {
        if (msg.sender != admin) revert NotAdmin(msg.sender);
        if (manager != address(0)) revert ManagerAlreadySet(manager);
        if (manager_ == address(0)) revert ZeroAddress();
        manager = manager_;
        emit ManagerSet(manager_);
    }

    /// @notice Register the caller as a user with reputation 0.5 (paper: addUser()).
    function addUser() external {
        User storage u = _users[msg.sender];
        if (u.registered) revert AlreadyRegistered(msg.sender);
        u.registered = true;
        u.reputation = uint64(Fixed.INITIAL_REPUTATION);
        emit UserAdded(msg.sender, Fixed.INITIAL_REPUTATION);
    }

    /// @notice Record that `numModels` of `user`'s models were allocated (paper: updateInfo()).
    /// @param user Owner of the allocated models.
    /// @param numModels Number of models allocated in this request.
    function updateInfo(address user, uint256 numModels) external onlyManager {
        User storage u = _registered(user);
        if (numModels == 0) revert ZeroCount();
        uint64 count = u.allocCount + uint64(numModels);
        u.allocCount = count;
        emit UserInfoUpdated(user, numModels, count);
    }

    /// @notice Add a review of one of `user`'s models and recompute Rep_i (paper: updateReputation()).
    /// @param user Owner of the reviewed model.
    /// @param review Review value, fixed point in [0, 1e18].
    function updateReputation(address user, uint256 review) external onlyManager {
        User storage u = _registered(user);
        if (review > Fixed.ONE) revert ReviewOutOfRange(review);
        uint256 total = uint256(u.totalReview) + review;
        uint256 count = u.allocCount;
        // Each allocation is reviewed at most once, so the total never exceeds count * 1.0.
        if (total > count * Fixed.ONE) revert ReviewsExceedAllocations(user);
        uint256 rep = total / count;
        u.totalReview = uint96(total);
        u.reputation = uint64(rep);
        emit UserReputationUpdated(user, review, total, rep);
    }

    /// @notice Whether `user` is registered.
    /// @param user Address to check.
    /// @return True when registered.
    function isRegistered(address user) external view returns (bool) {
        return _users[user].registered;
    }

    /// @notice Reputation of a registered user (fixed point, 1e18 = 1.0).
    /// @param user Registered address.
    /// @return Reputation Rep_i.
    function reputationOf(address user) external view returns (uint256) {
        return _registered(user).reputation;
    }

    /// @notice Full record of `user` (zeros when unregistered).
    /// @param user Address to read.
    /// @return registered Whether registered.
    /// @return reputation Rep_i, fixed point.
    /// @return allocCount Number of allocations of the user's models.
    /// @return totalReview Sum of the reviews of the user's models, fixed point.
    function getUser(address user)
        external
        view
        returns (bool registered, uint256 reputation, uint256 allocCount, uint256 totalReview)
    {
        User storage u = _users[user];
        return (u.registered, u.reputation, u.allocCount, u.totalReview);
    }

    function _registered(address user) private view returns (User storage u) {
        u = _users[user];
        if (!u.registered) revert UnregisteredUser(user);
    }
}
