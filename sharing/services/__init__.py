"""What sharing does to records and grants: one module per job. Every write of a Record,
Grant or AnchorRoot row is in one of these modules (the worker's integrity check marks a
record tampered, sharing/verification/tamper.py; an export's rows are sharing/exports/'s).

An action is one transaction; its chain work is queued on commit by task name
(core.outbox.enqueue) and done by the worker's tasks (sharing/tasks.py), which call
anchoring.py, grant_chain.py, sweep.py, reconcile.py and deletion.py.

- uploads.py: a robot's envelopes checked (header, key, tag, signature, sequence), stored
  durably, and their anchoring queued (record_create, record_create_batch).
- grants.py: an owner gives, changes and takes back access (grant_create, grant_terms_change,
  grant_revoke), and undoes what a revoked API token did to the grants.
- grant_chain.py: the chain made to agree with a grant (grant_sync_on_chain), run by the
  worker.
- anchoring.py: pending records' digests sent on chain in batches, one owner per run
  (ANCHOR_MODE=records), and the scheduling of those runs.
- roots.py: anchoring by Merkle roots (ANCHOR_MODE=root): trees built, written, sent.
- anchor_wait.py: what both anchoring modes share while they wait: the owner's lock kept,
  receipts awaited, gas, robots' keys not on chain yet.
- sweep.py: anchoring and grants that waited too long, queued again.
- reconcile.py: what the database says is on chain compared with the chain and repaired.
- deletion.py: records deleted (one, a selection, a robot's retention) and whole accounts,
  their ciphertext purged.
- completeness.py: records missing from a stream (a gap no deletion explains) told to the
  robot's owner, once per gap (records_missing_alerts_raise).
- backup.py: a portal's database, envelopes and secrets backed up to a folder and restored.

Import from the module that does the job; this package re-exports nothing.
"""
