//! The stepwise selection shared by the cycle diagnosis (docs/physics.md 4.6.1) and the
//! displacement diagnosis (4.7): forward selection, each step trying the best-ranked
//! candidates in turn until one passes the search's rules, then backward pruning of the terms
//! the later ones made redundant. What a term is worth and what it must pass are the search's
//! own ([`Scoring`]); the order of trials and the stopping rules are here, once.

/// A search's scoring of candidates against the model of the terms chosen so far.
pub(crate) trait Scoring {
    /// The candidates worth trying next to `chosen`, best first, with their score.
    fn rank(&mut self, chosen: &[usize]) -> Vec<(usize, f64)>;
    /// Whether candidate `i` (of score `score`) joins `chosen`.
    fn judge(&mut self, chosen: &[usize], i: usize, score: f64) -> Verdict;
    /// What each term of `chosen` is worth beyond the others (the score of dropping it), in
    /// the order of `chosen`.
    fn worth(&mut self, chosen: &[usize]) -> Vec<f64>;
    /// The term at `pos` of `chosen`, worth `score`, is about to be pruned.
    fn pruned(&mut self, _chosen: &[usize], _pos: usize, _score: f64) {}
}

/// A candidate's verdict in a forward step.
pub(crate) enum Verdict {
    /// It joins the model; the step ends.
    Take,
    /// It fails a rule; the next-ranked one is tried.
    Refuse,
    /// It fails a rule that the lower-ranked ones fail too; the step ends without a term.
    Stop,
}

/// The stopping rules.
pub(crate) struct Rules {
    /// At most this many terms.
    pub max_terms: usize,
    /// Candidates tried per forward step, best-ranked first.
    pub tries: usize,
    /// A term worth less than this is pruned.
    pub min_worth: f64,
}

/// Forward selection, then backward pruning: the chosen candidates, in the order taken.
/// A forward step that takes nothing ends the forward selection; pruning drops the least
/// worth term (the first of equals) while it is worth less than [`Rules::min_worth`].
pub(crate) fn stepwise(s: &mut impl Scoring, rules: &Rules) -> Vec<usize> {
    let mut chosen: Vec<usize> = Vec::new();
    while chosen.len() < rules.max_terms {
        let ranked = s.rank(&chosen);
        let mut took = None;
        for &(i, score) in ranked.iter().take(rules.tries) {
            match s.judge(&chosen, i, score) {
                Verdict::Take => {
                    took = Some(i);
                    break;
                }
                Verdict::Refuse => {}
                Verdict::Stop => break,
            }
        }
        match took {
            Some(i) => chosen.push(i),
            None => break,
        }
    }
    while !chosen.is_empty() {
        let weakest = s
            .worth(&chosen)
            .into_iter()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(&b.1));
        match weakest {
            Some((pos, w)) if w < rules.min_worth => {
                s.pruned(&chosen, pos, w);
                chosen.remove(pos);
            }
            _ => break,
        }
    }
    chosen
}
