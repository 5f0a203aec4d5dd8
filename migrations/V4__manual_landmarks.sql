-- The scan landmarks a result was fitted with when an operator placed them (their names,
-- comma-separated); NULL for an automatic fit.
ALTER TABLE captures ADD COLUMN landmarks TEXT;
