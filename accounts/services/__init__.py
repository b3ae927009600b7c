"""What accounts does to owners, their keys and robots: one module per job.

An action is one transaction; its chain work is queued on commit by task name
(core.outbox.enqueue) and done by the worker's tasks (accounts/tasks.py), which call
registration.py, robot_keys.py and funding.py.

- owners.py: sign-up (owner_create), an operator's approval, refusal, deactivation; an owner
  closing their account; the password asked again before a sensitive action.
- keys.py: the owners' SM4 keys: rotation, the check that a chosen key looks random,
  generation.
- robots.py: robots, their tokens and how long their records are kept.
- pairing.py: a robot paired by its SM2 key and the owner's approval, its token and the
  owner's key sent to it encrypted.
- api_tokens.py: owners' API tokens for their scripts (scopes, expiry, last use).
- funding.py: ether for owners' EOAs: registration funding within a budget, top-ups of
  owners low on gas.
- registration.py: owners' identity on chain, run by the worker: registration, key
  rotations, the sweep that queues them again, repair after the chain lost them or was reset
  (robots' keys included).
- robot_keys.py: paired robots' signing keys on chain: added once the pairing is approved,
  revoked once the robot is unpaired and the records it signed are anchored.
- activity.py: the audit page's index of owners' transactions.
- portal_secrets.py: the check of the portal's own secrets (the master key).

Import from the module that does the job; this package re-exports nothing.
"""
