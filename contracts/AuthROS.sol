// SPDX-License-Identifier: UNLICENSED
pragma solidity ^0.8.24;

/// @title AuthROS: authority and integrity anchor for encrypted ROS data
/// @notice Holds key commitments, record digests, owner-to-owner grants and the public keys
/// robots sign their records with. SM4 keys and ciphertexts never come here: only commitments
/// and SM3 digests.
contract AuthROS {
    /// @dev Slot 0 packs owner (20 bytes) with time (8 bytes); owner == 0 means "no record".
    struct Record {
        address owner;
        uint64 time;
        bytes32 digest;
        bytes32 dataType;
    }

    /// @dev A Merkle root as anchored by its sender; size 0 means "never anchored".
    struct Root {
        uint64 size;
        uint64 time;
        uint64 blockNumber;
    }

    /// @dev A grant's limits: `scope` is the SM3 commitment to the canonical encoding of the
    /// robots, topics and capture-time window it covers (docs/grants.md; 0 = all records),
    /// `expiry` the unix time (seconds) from which it no longer gives access (0 = never).
    struct GrantTerms {
        bytes32 scope;
        uint64 expiry;
    }

    /// @dev A robot's signing key (DESIGN.md "Provenance"), keyed by SM3 of its public key
    /// `x||y`: the first EOA that added it and the blocks of that addition and its revocation
    /// (0 = live). owner == 0 means "never added". What robotKeyOf answers, for old readers.
    struct RobotKey {
        address owner;
        uint64 addedBlock;
        uint64 revokedBlock;
    }

    /// @dev A robot key as one owner registered it: the blocks of its addition and revocation
    /// (0 = live); addedBlock == 0 means "this owner never added it". Never deleted, so an
    /// owner adds a key hash once; another owner's entry neither blocks nor replaces it.
    struct OwnerRobotKey {
        uint64 addedBlock;
        uint64 revokedBlock;
    }

    /// @dev Length of a robot's SM2 public key as robotKeyAdd takes it: `x||y`, no 04.
    uint256 private constant ROBOT_PUBLIC_KEY_LENGTH = 64;

    /// @notice Largest batch accepted by dataUploadBatch (keeps a full batch well under 30M gas).
    uint256 public constant MAX_BATCH = 256;

    /// @notice The deployer: the only account that may enroll EOAs.
    address public immutable admin;

    /// @notice Number of records anchored so far.
    uint256 public recordCount;

    /// @notice EOAs the admin has admitted to the private network.
    mapping(address eoa => bool) public isEnrolled;

    /// @notice Current key commitment of each registered EOA (zero until registered).
    mapping(address eoa => bytes32) public commitmentOf;

    /// @notice The last root each sender anchored (zero before its first): the next root of
    /// that sender must name it as prevRoot, so a sender's roots form one chain.
    mapping(address sender => bytes32) public lastRootOf;

    /// @dev Per-record digests keyed by (owner, id), as roots are keyed by sender: nobody can
    /// take another owner's record id first (issue 38). Key: _recordKey(owner, id).
    mapping(bytes32 ownerAndId => Record) private _records;
    mapping(address owner => mapping(address grantee => bool)) private _granted;
    mapping(address sender => mapping(bytes32 root => Root)) private _roots;
    /// @dev The terms of a grant: its scope commitment (0 = all records) and expiry (0 = none).
    mapping(address owner => mapping(address grantee => GrantTerms)) private _terms;
    mapping(bytes32 keyHash => RobotKey) private _robotKeys;
    /// @dev Robot keys by registering owner (issue 46): what a record's check asks, with the
    /// record's owner, so a key another owner registered first cannot take over its records.
    mapping(address owner => mapping(bytes32 keyHash => OwnerRobotKey)) private _ownerRobotKeys;

    event Enrolled(address indexed eoa);
    event Registered(address indexed eoa, bytes32 commitment);
    event KeyRotated(address indexed eoa, bytes32 oldCommitment, bytes32 newCommitment);
    event DataUploaded(
        bytes32 indexed id, address indexed owner, bytes32 digest, uint64 time, bytes32 dataType
    );
    event RootAnchored(
        address indexed sender, bytes32 indexed root, uint64 size, bytes32 prevRoot, uint64 time
    );
    event AuthorityGranted(address indexed owner, address indexed grantee);
    event AuthorityRevoked(address indexed owner, address indexed grantee);
    /// @notice A grant's terms were set (a new grant, or a change of an existing one).
    event AuthorityScoped(
        address indexed owner, address indexed grantee, bytes32 scope, uint64 expiry
    );
    /// @notice A robot's public key (`x||y`) was registered by its owner's EOA; with
    /// RobotKeyRevoked, every key an owner ever registered can be listed from logs alone.
    event RobotKeyAdded(address indexed owner, bytes32 indexed keyHash, bytes publicKey);
    event RobotKeyRevoked(address indexed owner, bytes32 indexed keyHash);

    error NotAdmin(address caller);
    error ZeroAddress();
    error AlreadyEnrolled(address eoa);
    error NotEnrolled(address caller);
    error AlreadyRegistered(address caller);
    error NotRegistered(address caller);
    error EmptyCommitment();
    error SameCommitment();
    error EmptyId();
    error EmptyDigest();
    error RecordExists(bytes32 id);
    error BatchLengthMismatch();
    error EmptyBatch();
    error BatchTooLarge(uint256 length, uint256 max);
    error GranteeNotRegistered(address grantee);
    error SelfGrant();
    error AlreadyGranted(address grantee);
    error NoGrant(address grantee);
    error ExpiryInPast(uint64 expiry, uint64 now_);
    error SameTerms(address grantee);
    error EmptyRoot();
    error EmptyTree();
    error RootExists(bytes32 root);
    error WrongPrevRoot(bytes32 expected, bytes32 given);
    error EmptyKeyHash();
    error WrongPublicKeyLength(uint256 length, uint256 expected);
    error RobotKeyExists(bytes32 keyHash);
    error RobotKeyUnknown(bytes32 keyHash);
    /// @dev Raised by deployments from before per-owner robot keys (a revocation by an EOA
    /// other than the key's first owner); kept so that their refusals still decode.
    error NotRobotKeyOwner(bytes32 keyHash, address caller);
    error RobotKeyAlreadyRevoked(bytes32 keyHash);

    modifier onlyRegistered() {
        if (commitmentOf[msg.sender] == 0) revert NotRegistered(msg.sender);
        _;
    }

    constructor() {
        admin = msg.sender;
    }

    /// @notice Admit an EOA to the network so that it may register.
    function enroll(address eoa) external {
        if (msg.sender != admin) revert NotAdmin(msg.sender);
        if (eoa == address(0)) revert ZeroAddress();
        if (isEnrolled[eoa]) revert AlreadyEnrolled(eoa);
        isEnrolled[eoa] = true;
        emit Enrolled(eoa);
    }

    /// @notice Bind the caller to its SM4 key through a commitment (never the key itself).
    function register(bytes32 commitment) external {
        if (!isEnrolled[msg.sender]) revert NotEnrolled(msg.sender);
        if (commitmentOf[msg.sender] != 0) revert AlreadyRegistered(msg.sender);
        if (commitment == 0) revert EmptyCommitment();
        commitmentOf[msg.sender] = commitment;
        emit Registered(msg.sender, commitment);
    }

    /// @notice Replace the caller's key commitment after a key rotation.
    function rotateKey(bytes32 commitment) external onlyRegistered {
        bytes32 old = commitmentOf[msg.sender];
        if (commitment == 0) revert EmptyCommitment();
        if (commitment == old) revert SameCommitment();
        commitmentOf[msg.sender] = commitment;
        emit KeyRotated(msg.sender, old, commitment);
    }

    /// @notice Anchor the digest of one record; each id can be written once per owner.
    function dataUpload(bytes32 id, bytes32 digest, uint64 time, bytes32 dataType)
        external
        onlyRegistered
    {
        _store(id, digest, time, dataType);
        unchecked {
            ++recordCount;
        }
    }

    /// @notice Anchor several records at once: all of them, or none.
    /// @dev Reverts with RecordExists naming the first taken id (earlier items of the same
    /// batch included), so the caller can drop it and retry.
    function dataUploadBatch(
        bytes32[] calldata ids,
        bytes32[] calldata digests,
        uint64[] calldata times,
        bytes32[] calldata types
    ) external onlyRegistered {
        uint256 n = ids.length;
        if (digests.length != n || times.length != n || types.length != n) {
            revert BatchLengthMismatch();
        }
        if (n == 0) revert EmptyBatch();
        if (n > MAX_BATCH) revert BatchTooLarge(n, MAX_BATCH);
        for (uint256 i; i < n; ) {
            _store(ids[i], digests[i], times[i], types[i]);
            unchecked {
                ++i;
            }
        }
        unchecked {
            recordCount += n;
        }
    }

    /// @notice Anchor the root of a Merkle tree of `size` records (DESIGN.md: SM3 leaves that
    /// bind owner, record id and digest). Roots are kept per sender, so nobody can take
    /// another sender's root first; `prevRoot` must be the sender's last root (zero for its
    /// first), so a lost or reordered root is refused rather than silently skipped.
    function anchorRoot(bytes32 root, uint64 size, bytes32 prevRoot) external {
        if (msg.sender != admin && commitmentOf[msg.sender] == 0) {
            revert NotRegistered(msg.sender);
        }
        if (root == 0) revert EmptyRoot();
        if (size == 0) revert EmptyTree();
        if (_roots[msg.sender][root].size != 0) revert RootExists(root);
        bytes32 last = lastRootOf[msg.sender];
        if (prevRoot != last) revert WrongPrevRoot(last, prevRoot);
        uint64 time = uint64(block.timestamp);
        _roots[msg.sender][root] = Root(size, time, uint64(block.number));
        lastRootOf[msg.sender] = root;
        emit RootAnchored(msg.sender, root, size, prevRoot, time);
    }

    /// @notice Let a registered grantee read the caller's records.
    function authorityGrant(address grantee) external onlyRegistered {
        if (grantee == msg.sender) revert SelfGrant();
        if (commitmentOf[grantee] == 0) revert GranteeNotRegistered(grantee);
        if (_granted[msg.sender][grantee]) revert AlreadyGranted(grantee);
        _granted[msg.sender][grantee] = true;
        emit AuthorityGranted(msg.sender, grantee);
    }

    /// @notice Let a registered grantee read those of the caller's records that `scope`
    /// covers, until `expiry`; or change the terms of the caller's grant to it. A grant made
    /// by authorityGrant has the terms (0, 0): all records, no expiry.
    function authorityGrantScoped(address grantee, bytes32 scope, uint64 expiry)
        external
        onlyRegistered
    {
        if (grantee == msg.sender) revert SelfGrant();
        if (commitmentOf[grantee] == 0) revert GranteeNotRegistered(grantee);
        if (expiry != 0 && expiry <= block.timestamp) {
            revert ExpiryInPast(expiry, uint64(block.timestamp));
        }
        GrantTerms storage terms = _terms[msg.sender][grantee];
        if (_granted[msg.sender][grantee]) {
            if (terms.scope == scope && terms.expiry == expiry) revert SameTerms(grantee);
        } else {
            _granted[msg.sender][grantee] = true;
            emit AuthorityGranted(msg.sender, grantee);
        }
        terms.scope = scope;
        terms.expiry = expiry;
        emit AuthorityScoped(msg.sender, grantee, scope, expiry);
    }

    /// @notice Withdraw a grant made earlier by the caller.
    function authorityRevoke(address grantee) external onlyRegistered {
        if (!_granted[msg.sender][grantee]) revert NoGrant(grantee);
        delete _granted[msg.sender][grantee];
        delete _terms[msg.sender][grantee];
        emit AuthorityRevoked(msg.sender, grantee);
    }

    /// @notice Register the public key (`x||y`, 64 bytes) a robot of the caller signs its
    /// records with, under `keyHash` = SM3(publicKey). SM3 costs too much gas to compute here,
    /// so the hash is not checked against the key: a verifier hashes the key it is given.
    /// Keys are kept per owner: an owner adds a hash once, ever (a revoked key cannot come
    /// back), and whatever another owner registered under the same hash changes nothing of
    /// it. robotKeyOf keeps the first owner that added the hash, for readers from before.
    function robotKeyAdd(bytes32 keyHash, bytes calldata publicKey) external onlyRegistered {
        if (keyHash == 0) revert EmptyKeyHash();
        if (publicKey.length != ROBOT_PUBLIC_KEY_LENGTH) {
            revert WrongPublicKeyLength(publicKey.length, ROBOT_PUBLIC_KEY_LENGTH);
        }
        OwnerRobotKey storage mine = _ownerRobotKeys[msg.sender][keyHash];
        if (mine.addedBlock != 0) revert RobotKeyExists(keyHash);
        uint64 blockNumber = uint64(block.number);
        mine.addedBlock = blockNumber;
        RobotKey storage first = _robotKeys[keyHash];
        if (first.owner == address(0)) {
            first.owner = msg.sender;
            first.addedBlock = blockNumber;
        }
        emit RobotKeyAdded(msg.sender, keyHash, publicKey);
    }

    /// @notice Revoke a robot key the caller added: records of the caller anchored from this
    /// block on no longer count as signed by it. Another owner's entry is left as it is.
    function robotKeyRevoke(bytes32 keyHash) external {
        OwnerRobotKey storage mine = _ownerRobotKeys[msg.sender][keyHash];
        if (mine.addedBlock == 0) revert RobotKeyUnknown(keyHash);
        if (mine.revokedBlock != 0) revert RobotKeyAlreadyRevoked(keyHash);
        uint64 blockNumber = uint64(block.number);
        mine.revokedBlock = blockNumber;
        RobotKey storage first = _robotKeys[keyHash];
        if (first.owner == msg.sender) first.revokedBlock = blockNumber;
        emit RobotKeyRevoked(msg.sender, keyHash);
    }

    /// @notice The caller's anchored record under `id`, or all zeros if it has none (yet).
    /// Record ids are bound to their owner: dataQueryOf reads another owner's.
    function dataQuery(bytes32 id)
        external
        view
        returns (address owner, bytes32 digest, uint64 time, bytes32 dataType)
    {
        return dataQueryOf(msg.sender, id);
    }

    /// @notice `owner`'s anchored record under `id`, or all zeros if it has none (yet).
    function dataQueryOf(address owner, bytes32 id)
        public
        view
        returns (address recordOwner, bytes32 digest, uint64 time, bytes32 dataType)
    {
        Record storage r = _records[_recordKey(owner, id)];
        return (r.owner, r.digest, r.time, r.dataType);
    }

    /// @notice True iff the caller anchored the record `id` with exactly this digest.
    function dataCheck(bytes32 id, bytes32 digest) external view returns (bool) {
        return dataCheckOf(msg.sender, id, digest);
    }

    /// @notice True iff `owner` anchored the record `id` with exactly this digest.
    function dataCheckOf(address owner, bytes32 id, bytes32 digest) public view returns (bool) {
        Record storage r = _records[_recordKey(owner, id)];
        return r.owner != address(0) && r.digest == digest;
    }

    /// @notice True iff viewer is the registered owner itself or holds a live grant from it
    /// (granted and not expired; a scoped grant counts: its scope is enforced at view).
    function hasAccess(address owner, address viewer) external view returns (bool) {
        if (owner == viewer) return commitmentOf[owner] != 0;
        return _granted[owner][viewer] && _unexpired(_terms[owner][viewer].expiry);
    }

    /// @notice The grant from `owner` to `grantee` in one call: whether it gives access now
    /// (granted and not expired), its scope commitment (0 = all records) and its expiry
    /// (0 = never). An expired grant answers live = false with its terms.
    function grantOf(address owner, address grantee)
        external
        view
        returns (bool live, bytes32 scope, uint64 expiry)
    {
        GrantTerms storage terms = _terms[owner][grantee];
        bool granted = _granted[owner][grantee];
        return (granted && _unexpired(terms.expiry), terms.scope, terms.expiry);
    }

    /// @notice A root as `sender` anchored it: size 0 if it never did.
    function rootOf(address sender, bytes32 root)
        external
        view
        returns (uint64 size, uint64 time, uint64 blockNumber)
    {
        Root storage r = _roots[sender][root];
        return (r.size, r.time, r.blockNumber);
    }

    /// @notice A robot key as `owner` registered it: the block it was added in (0: `owner`
    /// never added it) and the block it was revoked in (0 while live). What a record's check
    /// asks, with the record's owner (DESIGN.md "A record is genuine").
    function robotKeyOfOwner(address owner, bytes32 keyHash)
        external
        view
        returns (uint64 addedBlock, uint64 revokedBlock)
    {
        OwnerRobotKey storage key = _ownerRobotKeys[owner][keyHash];
        return (key.addedBlock, key.revokedBlock);
    }

    /// @notice A robot key as its first owner registered it: that EOA (zero if none did), the
    /// block it added it in, and the block it revoked it in (0 while live). Other owners may
    /// have registered the same key since: robotKeyOfOwner answers for each.
    function robotKeyOf(bytes32 keyHash)
        external
        view
        returns (address owner, uint64 addedBlock, uint64 revokedBlock)
    {
        RobotKey storage key = _robotKeys[keyHash];
        return (key.owner, key.addedBlock, key.revokedBlock);
    }

    /// @notice True iff the EOA has registered a key commitment.
    function isRegistered(address eoa) external view returns (bool) {
        return commitmentOf[eoa] != 0;
    }

    function _unexpired(uint64 expiry) private view returns (bool) {
        return expiry == 0 || block.timestamp < expiry;
    }

    function _store(bytes32 id, bytes32 digest, uint64 time, bytes32 dataType) private {
        if (id == 0) revert EmptyId();
        if (digest == 0) revert EmptyDigest();
        bytes32 key = _recordKey(msg.sender, id);
        if (_records[key].owner != address(0)) revert RecordExists(id);
        _records[key] = Record(msg.sender, time, digest, dataType);
        emit DataUploaded(id, msg.sender, digest, time, dataType);
    }

    function _recordKey(address owner, bytes32 id) private pure returns (bytes32) {
        return keccak256(abi.encode(owner, id));
    }
}
