-- The build that scored a finished submission: `dsrl-leaderboard <version> (git <commit>[-modified])`, the scorer's
-- commit marked where its scoring-path sources differed from it. NULL for results scored before it was recorded.
ALTER TABLE submissions ADD COLUMN scored_by TEXT;
