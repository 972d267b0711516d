"""The contract both daemons import: shapes, the sample byte format and the spool. No torch here."""
