"""The estimators, pure functions of a scan's points and energies: split (eq. 10–12), correct (eq. 9),
LEL (eq. 6–8), LS, FCM + RANSAC, the quality verdict, and the corner model (:mod:`.corner`)."""
