// SPDX-License-Identifier: Apache-2.0
pragma solidity 0.8.28;

import {Fixed, ReviewOutOfRange, UnregisteredUser} from "./MedcShared.sol";
import {UsersManager} from "./UsersManager.sol";

/// @title Models Manager Contract (MMC)
/// @notice Shared MDRL models, their greedy allocation by QoS, payments and reviews (paper Table II):
///         Rep_m = Total Model Review / Allocation Count; QoS_m = Rep_i * Rep_m / D_m;
///         D_m = sum_i w_i |E_i^m - E_i^r| with sum_i w_i = 1 (equal weights by default).
///         All reputations, weights and QoS are fixed point with 1e18 = 1.0.
/// @dev Payments are pull-based: allocations credit the owners (and refunds credit the requester),
///      and `withdraw` pays out, so the contract balance always equals the sum of what is owed.
contract ModelsManager {
    /// @notice Upper bound on the number of environment features of an application.
    /// @dev The features of a model are packed into one storage word, 32 bits each.
    uint256 internal constant MAX_FEATURES = 8;
    /// @notice Upper bound on the length of a CID string.
    uint256 internal constant MAX_CID_LENGTH = 128;
    /// @notice Upper bound on the candidate models one allocation examines (bounds its gas: about
    ///         8,300 gas per candidate, so at most ~2.1 M gas of ranking per call).
    /// @dev For an application with more models, the requester ranks them in pages with free
    ///      simulated calls (eth_call) of `allocateModels` itself, each page together with the
    ///      best so far, and then passes the overall best positions as `candidates`.
    uint256 internal constant MAX_CANDIDATES = 256;

    /// @dev Slot 0: owner, reputation, allocCount. Slot 1: totalReview, price, appId.
    ///      Slot 2: environment details E^m, feature i in bits [32 i, 32 i + 32).
    struct Model {
        address owner;
        uint64 reputation;
        uint32 allocCount;
        uint96 totalReview;
        uint128 price;
        uint32 appId;
        uint256 env;
        string cid;
        string description;
    }

    /// @dev One slot per allocation: who may review which model, and whether they did.
    struct Allocation {
        address requester;
        uint32 modelId;
        bool reviewed;
    }

    /// @dev Best candidates so far, best first. A key is QoS_m, or for an exact environment match
    ///      (D_m = 0) the top bit set over Rep_i * Rep_m, so exact matches outrank every finite QoS.
    struct Ranking {
        uint256[] ids;
        uint256[] keys;
        uint256 found;
    }

    /// @notice The Users Manager this contract reports allocations and reviews to.
    UsersManager public immutable users;

    Model[] private _models;
    Allocation[] private _allocations;
    string[] private _appNames; // appId - 1 -> name
    mapping(bytes32 => uint32) private _appIdOf; // keccak(name) -> appId (0 = unknown)
    mapping(uint32 => uint8) private _featureCount; // appId -> number of environment features
    mapping(uint32 => uint32[]) private _modelsList; // appId -> model ids (paper: Models List)
    mapping(address => uint256) private _owed;
    /// @dev keccak(requester, requestId) -> (block number << 128) | (firstAllocationId + 1),
    ///      0 = not paid yet: where a paid request's allocations are, in one slot.
    mapping(bytes32 => uint256) private _requests;

    error UnknownModel(uint256 modelId);
    /// @dev No argument: eth-tester reads ABI-encoded string payloads as revert reasons.
    error UnknownApplication();
    error UnknownAllocation(uint256 allocationId);
    error EmptyApplication();
    error InvalidCid(uint256 length);
    error TooManyFeatures(uint256 given, uint256 maximum);
    error FeatureCountMismatch(uint256 expected, uint256 given);
    error InvalidWeights(uint256 count, uint256 sum);
    error PriceTooLarge(uint256 price);
    error InvalidCount();
    error NoEligibleModels();
    error InsufficientPayment(uint256 required, uint256 sent);
    error RequestAlreadyPaid(uint256 firstAllocationId);
    error TooManyCandidates(uint256 given, uint256 maximum);
    error InvalidCandidate(uint256 position);
    error NotAllocatedRequester(uint256 allocationId, address caller);
    error AlreadyReviewed(uint256 allocationId);
    error NothingToWithdraw(address account);
    error TransferFailed(address account, uint256 amount);

    event ApplicationAdded(uint256 indexed appId, string application, uint256 featureCount);
    event ModelAdded(
        uint256 indexed modelId, address indexed owner, uint256 indexed appId, string cid, uint256 price
    );
    event ModelAllocated(
        uint256 indexed allocationId,
        uint256 indexed modelId,
        address indexed requester,
        address owner,
        uint256 price,
        uint256 qos,
        uint256 distance
    );
    event PaymentCredited(address indexed account, uint256 amount, uint256 owed);
    event ModelReviewed(
        uint256 indexed allocationId, uint256 indexed modelId, address indexed requester, uint256 review, uint256 reputation
    );
    event Withdrawn(address indexed account, uint256 amount);

    constructor(UsersManager users_) {
        users = users_;
    }

    /// @notice Share a model (paper: addModel()). The caller must be a registered user.
    /// @param application Application name (e.g. "target_localization").
    /// @param cid IPFS CID of the model file.
    /// @param description Free text: architecture, input requirements, feature names.
    /// @param envDetails Environment features E^m; every model of an application has the same count.
    /// @param price Price in wei a requester pays when the model is allocated.
    /// @return modelId Identifier of the new model.
    function addModel(
        string calldata application,
        string calldata cid,
        string calldata description,
        uint32[] calldata envDetails,
        uint256 price
    ) external returns (uint256 modelId) {
        _requireRegistered();
        uint256 cidLength = bytes(cid).length;
        if (cidLength == 0 || cidLength > MAX_CID_LENGTH) revert InvalidCid(cidLength);
        if (price > type(uint128).max) revert PriceTooLarge(price);
        uint32 appId = _appIdOrCreate(application, envDetails.length);

        modelId = _models.length;
        Model storage m = _models.push();
        m.owner = msg.sender;
        m.reputation = uint64(Fixed.INITIAL_REPUTATION);
        m.price = uint128(price);
        m.appId = appId;
        m.cid = cid;
        if (bytes(description).length != 0) m.description = description;
        m.env = _pack(envDetails);
        _modelsList[appId].push(uint32(modelId));
        emit ModelAdded(modelId, msg.sender, appId, cid, price);
    }

    /// @notice Allocate up to `count` models to the caller (paper: allocateModels()), paying their prices.
    /// @dev Greedy: keep the candidates whose reputation and owner reputation meet the minimums
    ///      (never the caller's own), rank exact environment matches (D_m = 0) first by
    ///      Rep_i * Rep_m, then the rest by QoS_m, ties by lower model id, and take the best `count`.
    ///      One pass over the candidates with an insertion into a top-`count` list.
    ///      The candidates are positions in the application's Models List that the requester
    ///      passes (1 to MAX_CANDIDATES, strictly increasing): all of them when there are few,
    ///      else the overall top `count` found by simulating this function page by page, so one
    ///      call's gas is bounded however many models were shared.
    ///      Idempotent: `requestId` (chosen by the requester) is recorded with the allocation; the
    ///      same requester sending the same id again reverts with
    ///      RequestAlreadyPaid(firstAllocationId) before any other check, and pays
    ///      nothing. A simulated call (eth_call) with the id tells whether it was paid.
    ///      The caller must send at least the sum of the allocated models' prices; the excess is
    ///      credited back to the caller (withdraw it).
    /// @param requestId Requester-chosen idempotency key.
    /// @param application Application name.
    /// @param requirements Requester's environment features E^r (same count as the application's).
    /// @param weights Feature weights w_i summing to 1e18, or empty for equal weights.
    /// @param count Number of models wanted.
    /// @param minModelRep Minimum model reputation (fixed point).
    /// @param minOwnerRep Minimum owner reputation (fixed point).
    /// @param candidates Positions in the application's Models List to rank: 1 to MAX_CANDIDATES, increasing.
    /// @return modelIds Allocated models, best first.
    /// @return firstAllocationId Allocation id of modelIds[0]; the others follow consecutively.
    function allocateModels(
        bytes32 requestId,
        string calldata application,
        uint32[] calldata requirements,
        uint256[] calldata weights,
        uint256 count,
        uint256 minModelRep,
        uint256 minOwnerRep,
        uint256[] calldata candidates
    ) external payable returns (uint256[] memory modelIds, uint256 firstAllocationId) {
        bytes32 requestKey = _requestKey(msg.sender, requestId);
        uint256 record = _requests[requestKey];
        if (record != 0) revert RequestAlreadyPaid(uint128(record) - 1);
        uint32 appId = _checkRequest(application, requirements, weights, count);

        Ranking memory r = _rank(
            _modelsList[appId], candidates, requirements, weights, count, minModelRep, minOwnerRep
        );
        uint256 found = r.found;
        if (found == 0) revert NoEligibleModels();

        uint256 total;
        for (uint256 j; j < found; ++j) {
            total += _models[r.ids[j]].price;
        }
        if (msg.value < total) revert InsufficientPayment(total, msg.value);

        // Effects first; the only external calls below go to the trusted Users Manager.
        firstAllocationId = _allocations.length;
        modelIds = new uint256[](found);
        for (uint256 j; j < found; ++j) {
            uint256 id = r.ids[j];
            Model storage m = _models[id];
            m.allocCount += 1;
            _allocations.push(Allocation({requester: msg.sender, modelId: uint32(id), reviewed: false}));
            modelIds[j] = id;
            address owner = m.owner;
            uint256 price = m.price;
            uint256 key = r.keys[j];
            uint256 qos = key >> 255 == 1 ? type(uint256).max : key;
            uint256 dist = _distance(m.env, requirements, weights);
            emit ModelAllocated(firstAllocationId + j, id, msg.sender, owner, price, qos, dist);
            if (price != 0) _credit(owner, price);
        }
        if (msg.value > total) _credit(msg.sender, msg.value - total);
        _requests[requestKey] = (block.number << 128) | (firstAllocationId + 1);
        for (uint256 j; j < found; ++j) {
            users.updateInfo(_models[r.ids[j]].owner, 1);
        }
    }

    /// @notice Review an allocated model (paper: updateModelRep()); updates Rep_m and the owner's Rep_i.
    /// @dev Only the requester of the allocation, once, with a value in [0, 1e18].
    /// @param allocationId Allocation being reviewed.
    /// @param review Review value, fixed point in [0, 1e18].
    function updateModelRep(uint256 allocationId, uint256 review) external {
        if (allocationId >= _allocations.length) revert UnknownAllocation(allocationId);
        Allocation storage a = _allocations[allocationId];
        if (a.requester != msg.sender) revert NotAllocatedRequester(allocationId, msg.sender);
        if (a.reviewed) revert AlreadyReviewed(allocationId);
        if (review > Fixed.ONE) revert ReviewOutOfRange(review);
        a.reviewed = true;
        uint256 modelId = a.modelId;
        Model storage m = _models[modelId];
        uint256 total = uint256(m.totalReview) + review;
        uint256 rep = total / m.allocCount;
        m.totalReview = uint96(total);
        m.reputation = uint64(rep);
        emit ModelReviewed(allocationId, modelId, msg.sender, review, rep);
        users.updateReputation(m.owner, review);
    }

    /// @notice Pay out everything owed to the caller (model payments and refunds).
    function withdraw() external {
        uint256 amount = _owed[msg.sender];
        if (amount == 0) revert NothingToWithdraw(msg.sender);
        _owed[msg.sender] = 0;
        emit Withdrawn(msg.sender, amount);
        (bool ok,) = payable(msg.sender).call{value: amount}("");
        if (!ok) revert TransferFailed(msg.sender, amount);
    }

    /// @notice Amount (wei) `account` can withdraw.
    /// @param account Address to read.
    /// @return Owed amount in wei.
    function owed(address account) external view returns (uint256) {
        return _owed[account];
    }

    /// @notice Number of shared models (ids are 0 .. modelCount - 1).
    /// @return Model count.
    function modelCount() external view returns (uint256) {
        return _models.length;
    }

    /// @notice Number of allocations made so far.
    /// @return Allocation count.
    function allocationCount() external view returns (uint256) {
        return _allocations.length;
    }

    /// @notice Numeric details of model `modelId`.
    /// @param modelId Model id.
    /// @return owner Owner address.
    /// @return appId Application id (name: `applicationName(appId)`).
    /// @return envDetails Environment features E^m.
    /// @return price Price in wei.
    /// @return reputation Rep_m, fixed point.
    /// @return allocCount Number of allocations of the model.
    /// @return totalReview Sum of its reviews, fixed point.
    function getModel(uint256 modelId)
        external
        view
        returns (
            address owner,
            uint256 appId,
            uint32[] memory envDetails,
            uint256 price,
            uint256 reputation,
            uint256 allocCount,
            uint256 totalReview
        )
    {
        Model storage m = _model(modelId);
        return (m.owner, m.appId, _unpack(m.env, _featureCount[m.appId]), m.price, m.reputation, m.allocCount, m.totalReview);
    }

    /// @notice CID and description of model `modelId`.
    /// @param modelId Model id.
    /// @return cid IPFS CID of the model file.
    /// @return description Free-text description given when sharing.
    function getModelText(uint256 modelId) external view returns (string memory cid, string memory description) {
        Model storage m = _model(modelId);
        return (m.cid, m.description);
    }

    /// @notice Name of application `appId` (ids start at 1).
    /// @param appId Application id.
    /// @return Application name (empty for an unknown id).
    function applicationName(uint256 appId) external view returns (string memory) {
        if (appId == 0 || appId > _appNames.length) return "";
        return _appNames[appId - 1];
    }

    /// @notice Allocation record `allocationId`.
    /// @param allocationId Allocation id.
    /// @return requester Who was allocated the model.
    /// @return modelId The allocated model.
    /// @return reviewed Whether the requester reviewed it.
    function getAllocation(uint256 allocationId)
        external
        view
        returns (address requester, uint256 modelId, bool reviewed)
    {
        if (allocationId >= _allocations.length) revert UnknownAllocation(allocationId);
        Allocation storage a = _allocations[allocationId];
        return (a.requester, a.modelId, a.reviewed);
    }

    /// @notice Whether `requester` paid request `requestId` (see `allocateModels`), and where.
    /// @param requester Who sent the request.
    /// @param requestId The request's idempotency key.
    /// @return paid Whether the request was paid and allocated.
    /// @return firstAllocationId Allocation id of its first model; the others follow (0 if unpaid).
    /// @return blockNumber Block of the transaction that paid it (0 if unpaid).
    function paidRequest(address requester, bytes32 requestId)
        external
        view
        returns (bool paid, uint256 firstAllocationId, uint256 blockNumber)
    {
        uint256 record = _requests[_requestKey(requester, requestId)];
        if (record == 0) return (false, 0, 0);
        return (true, uint128(record) - 1, record >> 128);
    }

    function _appIdOrCreate(string calldata application, uint256 features) private returns (uint32 appId) {
        if (bytes(application).length == 0) revert EmptyApplication();
        if (features > MAX_FEATURES) revert TooManyFeatures(features, MAX_FEATURES);
        bytes32 key = keccak256(bytes(application));
        appId = _appIdOf[key];
        if (appId == 0) {
            _appNames.push(application);
            appId = uint32(_appNames.length);
            _appIdOf[key] = appId;
            _featureCount[appId] = uint8(features);
            emit ApplicationAdded(appId, application, features);
        } else if (_featureCount[appId] != features) {
            revert FeatureCountMismatch(_featureCount[appId], features);
        }
    }

    /// @dev Reverts UnregisteredUser unless the caller is a registered user (one call site of the
    ///      Users Manager for both addModel and allocateModels).
    function _requireRegistered() private view {
        if (!users.isRegistered(msg.sender)) revert UnregisteredUser(msg.sender);
    }

    /// @dev Where the record of `requester`'s request `requestId` is kept in `_requests`.
    function _requestKey(address requester, bytes32 requestId) private pure returns (bytes32) {
        return keccak256(abi.encode(requester, requestId));
    }

    function _model(uint256 modelId) private view returns (Model storage) {
        if (modelId >= _models.length) revert UnknownModel(modelId);
        return _models[modelId];
    }

    function _credit(address account, uint256 amount) private {
        uint256 balance = _owed[account] + amount;
        _owed[account] = balance;
        emit PaymentCredited(account, amount, balance);
    }

    /// @dev The request's checks; returns the application id.
    function _checkRequest(
        string calldata application,
        uint32[] calldata requirements,
        uint256[] calldata weights,
        uint256 count
    ) private view returns (uint32 appId) {
        _requireRegistered();
        appId = _appIdOf[keccak256(bytes(application))];
        if (appId == 0) revert UnknownApplication();
        if (count == 0) revert InvalidCount();
        uint256 p = _featureCount[appId];
        if (requirements.length != p) revert FeatureCountMismatch(p, requirements.length);
        _checkWeights(weights, p);
    }

    function _checkWeights(uint256[] calldata weights, uint256 p) private pure {
        if (weights.length == 0) return;
        uint256 sum;
        for (uint256 i; i < weights.length; ++i) {
            sum += weights[i];
        }
        if (weights.length != p || sum != Fixed.ONE) revert InvalidWeights(weights.length, sum);
    }

    function _pack(uint32[] calldata values) private pure returns (uint256 word) {
        for (uint256 i; i < values.length; ++i) {
            word |= uint256(values[i]) << (32 * i);
        }
    }

    function _unpack(uint256 word, uint256 count) private pure returns (uint32[] memory values) {
        values = new uint32[](count);
        for (uint256 i; i < count; ++i) {
            values[i] = uint32(word >> (32 * i));
        }
    }

    /// @dev D_m in fixed point (1e18 = one feature unit). Equal weights: sum |diff| / p.
    function _distance(uint256 env, uint32[] calldata req, uint256[] calldata weights)
        private
        pure
        returns (uint256 d)
    {
        uint256 p = req.length;
        if (weights.length == 0) {
            uint256 sum;
            for (uint256 i; i < p; ++i) {
                (uint256 a, uint256 b) = (uint32(env >> (32 * i)), req[i]);
                sum += a > b ? a - b : b - a;
            }
            return p == 0 ? 0 : (sum * Fixed.ONE) / p;
        }
        for (uint256 i; i < p; ++i) {
            (uint256 a, uint256 b) = (uint32(env >> (32 * i)), req[i]);
            d += weights[i] * (a > b ? a - b : b - a);
        }
    }

    /// @dev One pass over the candidates keeping the best `count` (insertion into a sorted list).
    ///      `positions` index the application's Models List `list`: 1 to MAX_CANDIDATES of them,
    ///      strictly increasing, so no model is ranked (or paid) twice.
    function _rank(
        uint32[] storage list,
        uint256[] calldata positions,
        uint32[] calldata requirements,
        uint256[] calldata weights,
        uint256 count,
        uint256 minModelRep,
        uint256 minOwnerRep
    ) private view returns (Ranking memory r) {
        uint256 n = positions.length;
        if (n == 0 || n > MAX_CANDIDATES) revert TooManyCandidates(n, MAX_CANDIDATES);
        uint256 listLength = list.length;
        if (count > n) count = n;
        r.ids = new uint256[](count);
        r.keys = new uint256[](count);
        for (uint256 c; c < n; ++c) {
            uint256 pos = positions[c];
            if (pos >= listLength || (c != 0 && pos <= positions[c - 1])) revert InvalidCandidate(pos);
            uint256 id = list[pos];
            Model storage m = _models[id];
            address owner = m.owner;
            uint256 mRep = m.reputation;
            if (mRep < minModelRep || owner == msg.sender) continue;
            uint256 oRep = users.reputationOf(owner);
            if (oRep < minOwnerRep) continue;
            uint256 dist = _distance(m.env, requirements, weights);
            uint256 repProduct = (oRep * mRep) / Fixed.ONE;
            // D_m = 0 ranks above every finite QoS; among exact matches the reputations decide.
            _insert(r, id, dist == 0 ? (1 << 255) | repProduct : (repProduct * Fixed.ONE) / dist);
        }
    }

    /// @dev Insert a candidate into the ranking; equal keys keep the earlier (lower) id first.
    function _insert(Ranking memory r, uint256 id, uint256 key) private pure {
        uint256 cap = r.ids.length;
        uint256 pos = r.found;
        while (pos > 0 && r.keys[pos - 1] < key) {
            if (pos < cap) {
                r.ids[pos] = r.ids[pos - 1];
                r.keys[pos] = r.keys[pos - 1];
            }
            --pos;
        }
        if (pos >= cap) return;
        r.ids[pos] = id;
        r.keys[pos] = key;
        if (r.found < cap) r.found += 1;
    }
}
