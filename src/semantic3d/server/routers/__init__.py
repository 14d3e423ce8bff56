"""One router per resource: challenges, accounts, uploads, submissions, admin."""
