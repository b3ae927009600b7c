"""What sharing reads (nothing here writes): one module per resource.

- records.py: the records a viewer may see (their own, and those live grants cover), the
  record lists' filters and sorts, a record page's neighbours and proof, the fixed reads of a
  record a view opens and the worker checks.
- grants.py: grants that let a viewer read now, an owner's grants given and received, those an
  owner API token made or changed, and the owner a grant names (owner_resolve).
- access.py: the access log, incoming and outgoing, its filters, a viewer's latest verdict.
- activity.py: an owner's transactions (the audit page) and alarms, and the chain work
  waiting (the operator's status, the metrics).
- exports.py: an owner's exports, and those unfinished (the metrics).

Import from the module that does the job; this package re-exports nothing.
"""
