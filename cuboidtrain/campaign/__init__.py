"""The GPU campaign (issue 40): one standing run that every lent GPU minute continues, its state in the repository's campaign/."""
