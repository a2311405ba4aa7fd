"""The database's schema history (Alembic revisions in ``versions/``, the environment in ``env.py``; no alembic.ini).

Run by :func:`service.db.migrate`; how to add a revision: :mod:`service.db`. Revision ids never change: a database
records the id it is at, so a renamed or renumbered revision would strand it.
"""
