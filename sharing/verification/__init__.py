"""The integrity check at view time, and reading records' content through it: one module per
job, one path for any number of records (the single record being N = 1).

- check.py: the worker's check (`records_verify`, the task sharing.tasks.records_verify):
  access on chain, each stored envelope's SM3 against the chain, a signed record's robot
  signature and key, a Verdict each; and the answer it hands back to the web.
- grant_on_chain.py: whether a viewer may read an owner's records now, the portal's grant
  and the chain's (`grantOf`) compared.
- tamper.py: what a failed check does (the record marked, a SecurityEvent, the owner's alert,
  the cached copy dropped).
- access.py: the access log's lines for a read (`Access`, one per record owner), the
  credential check, and the coalescing of refused views.
- opening.py: the web's side (`records_open`, `record_open`): the records sent to the worker
  in batches, the bytes it checked decrypted once, re-sealed for the viewer; a series'
  slices sent to the series task and its sealed rows opened (`records_rows_open`).
- series_check.py: the worker's side of a series (the task sharing.tasks.series_verify): a
  slice checked by records_verify, only the verified records' plotted numbers handed back.
- answers.py: a read's answer sealed between the web and the worker (a per-read SM4 key
  wrapped under the KEK), so that no plaintext sits in the result backend.
- keys.py: the records' SM4 keys, unwrapped once per key for a read, a check or an export.
- signature.py: a record's robot signature facts for its proof and for an export's bundle.

Import from the module that does the job; this package re-exports nothing.
"""
