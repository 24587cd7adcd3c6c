"""Follow-the-leader driving: the operator steers the tip, the body follows its trail."""
