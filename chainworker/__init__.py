"""The chain layer: the AuthROS contract's client and the chain work the apps share.

One module per job:

- `client`: `AuthROSChain`, the one client of the contract (its functions by name);
- `sender`: building, signing and sending transactions, and awaiting their receipts;
- `rpc`: the connection to the node and the raw JSON-RPC requests sent on it;
- `codec`: the contract's values, results and ABI (calldata, outputs, errors, events);
- `errors`: `ChainError` and its kinds, and the translation of the node's failures;
- `nonces`: nonces for locally signed transactions, shared across processes;
- `gas`: the accounts running low on gas, as the apps list them for the admin;
- `work`: the lock, retry policy and not-ready error every chain task shares;
- `backlog`: what the apps register as waiting for the chain;
- `services`, `selectors`: the client per process, the operator, deployments and status;
- `models`, `admin`, `management/commands`: deployments and operator alerts, their admin
  pages, chain_deploy and chain_status.

Import from the module that does the job; this package re-exports nothing.
"""
