"""Exports: the verified records of a selection as an MCAP file, with a proof bundle beside it
(docs/export.md), one module per job.

- selection.py: what a requester may export (robots, topics, the records of a selection they
  may view) and how many that is; an export's selection described for its page.
- create.py: an export asked for (`export_create`, `export_rebuild`), its run queued on commit.
- run.py: the export made on a worker (`export_run`): each batch checked with the view's
  own integrity check, the records that fail left out and listed, both files written sealed.
- withdraw.py: the access an export's requester must keep (`export_access_lost`), its
  withdrawal, expiry and the periodic sweep (`exports_sweep`, `exports_recheck`).
- download.py: an export's files streamed to its requester, decrypted as read.
- files.py: where the files live, their names, their key's purpose, their removal.

Nothing of an export is plaintext at rest: its files are sealed under a key of its own, wrapped
by the KEK and removed when the export ends. Import from the module that does the job; this
package re-exports nothing.
"""
