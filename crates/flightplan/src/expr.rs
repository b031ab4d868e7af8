//! The condition language of flight plans: booleans and numbers, `and` / `or` / `not`,
//! comparisons, parentheses, plan variables and built-ins. Parsed once, type-checked against the
//! declared variables at load time, so evaluation cannot fail.
//!
//! ```text
//! or   := and (("or" | "||") and)*
//! and  := not (("and" | "&&") not)*
//! not  := ("not" | "!") not | cmp
//! cmp  := atom (("<" | "<=" | ">" | ">=" | "==" | "=" | "!=") atom)?
//! atom := number | "true" | "false" | identifier | "(" or ")" | "-" atom
//! ```

use serde::{Deserialize, Serialize};
use std::fmt;
use thiserror::Error;

/// A run-time value of a plan variable.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Value {
    /// A boolean.
    Bool(bool),
    /// A number (all numbers are f64).
    Number(f64),
}

impl Value {
    /// The value's type.
    pub fn ty(&self) -> ValueType {
        match self {
            Value::Bool(_) => ValueType::Bool,
            Value::Number(_) => ValueType::Number,
        }
    }
    /// Parses a value of type `ty` from its text form (`true`, `false`, or a number).
    pub fn parse(ty: ValueType, s: &str) -> Option<Value> {
        match ty {
            ValueType::Bool => match s.trim() {
                "true" => Some(Value::Bool(true)),
                "false" => Some(Value::Bool(false)),
                _ => None,
            },
            ValueType::Number => s
                .trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .map(Value::Number),
        }
    }
}

impl fmt::Display for Value {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Value::Bool(b) => write!(f, "{b}"),
            Value::Number(n) => write!(f, "{n}"),
        }
    }
}

/// The type of a variable or expression.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ValueType {
    /// `true` / `false`.
    Bool,
    /// A real number.
    Number,
}

impl fmt::Display for ValueType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            ValueType::Bool => "bool",
            ValueType::Number => "number",
        })
    }
}

/// A comparison operator.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum CmpOp {
    /// `<`
    Lt,
    /// `<=`
    Le,
    /// `>`
    Gt,
    /// `>=`
    Ge,
    /// `==` or `=`
    Eq,
    /// `!=`
    Ne,
}

/// A parsed expression.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Expr {
    /// A literal.
    Lit(Value),
    /// A variable (plan variable or built-in).
    Var(String),
    /// Numeric negation.
    Neg(Box<Expr>),
    /// Logical not.
    Not(Box<Expr>),
    /// Logical and.
    And(Box<Expr>, Box<Expr>),
    /// Logical or.
    Or(Box<Expr>, Box<Expr>),
    /// A comparison.
    Cmp(CmpOp, Box<Expr>, Box<Expr>),
}

/// Why a condition could not be parsed or type-checked.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum ExprError {
    /// A token that does not fit the grammar.
    #[error("condition `{src}`: unexpected {found} at character {offset}")]
    Unexpected {
        /// The condition text.
        src: String,
        /// What was found.
        found: String,
        /// Character offset in the condition.
        offset: usize,
    },
    /// A variable that is neither declared nor a built-in.
    #[error("condition uses unknown variable `{0}`")]
    UnknownVariable(String),
    /// An operator applied to the wrong type.
    #[error("condition: {op} needs {expected} operands, found {found}")]
    TypeMismatch {
        /// The operator.
        op: &'static str,
        /// The type it needs.
        expected: ValueType,
        /// The type it got.
        found: ValueType,
    },
    /// The whole condition is not boolean.
    #[error("condition must be true or false, this one is a number")]
    NotBoolean,
}

#[derive(Clone, Debug, PartialEq)]
enum Tok {
    Num(f64),
    Ident(String),
    Op(&'static str),
}

fn tokenize(src: &str) -> Result<Vec<(Tok, usize)>, ExprError> {
    let chars: Vec<char> = src.chars().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < chars.len() {
        let c = chars[i];
        if c.is_whitespace() {
            i += 1;
            continue;
        }
        let start = i;
        if c.is_ascii_digit() || (c == '.' && chars.get(i + 1).is_some_and(|d| d.is_ascii_digit()))
        {
            while i < chars.len()
                && (chars[i].is_ascii_digit()
                    || chars[i] == '.'
                    || chars[i] == 'e'
                    || chars[i] == 'E'
                    || ((chars[i] == '-' || chars[i] == '+')
                        && i > start
                        && matches!(chars[i - 1], 'e' | 'E')))
            {
                i += 1;
            }
            let text: String = chars[start..i].iter().collect();
            let v = text.parse::<f64>().map_err(|_| ExprError::Unexpected {
                src: src.to_string(),
                found: format!("`{text}`"),
                offset: start,
            })?;
            out.push((Tok::Num(v), start));
            continue;
        }
        if c.is_alphabetic() || c == '_' {
            while i < chars.len()
                && (chars[i].is_alphanumeric() || chars[i] == '_' || chars[i] == '.')
            {
                i += 1;
            }
            out.push((Tok::Ident(chars[start..i].iter().collect()), start));
            continue;
        }
        let two: String = chars[i..(i + 2).min(chars.len())].iter().collect();
        let op = match two.as_str() {
            "<=" => Some("<="),
            ">=" => Some(">="),
            "==" => Some("=="),
            "!=" => Some("!="),
            "&&" => Some("and"),
            "||" => Some("or"),
            _ => None,
        };
        if let Some(op) = op {
            out.push((Tok::Op(op), start));
            i += 2;
            continue;
        }
        let op = match c {
            '<' => "<",
            '>' => ">",
            '=' => "==",
            '!' => "not",
            '(' => "(",
            ')' => ")",
            '-' => "-",
            _ => {
                return Err(ExprError::Unexpected {
                    src: src.to_string(),
                    found: format!("`{c}`"),
                    offset: start,
                })
            }
        };
        out.push((Tok::Op(op), start));
        i += 1;
    }
    Ok(out)
}

struct Parser<'a> {
    src: &'a str,
    toks: Vec<(Tok, usize)>,
    pos: usize,
    depth: usize,
}

/// Nesting beyond this is refused so random input cannot overflow the stack.
const MAX_DEPTH: usize = 64;

impl Parser<'_> {
    fn err(&self) -> ExprError {
        match self.toks.get(self.pos) {
            Some((t, off)) => ExprError::Unexpected {
                src: self.src.to_string(),
                found: match t {
                    Tok::Num(n) => format!("`{n}`"),
                    Tok::Ident(s) => format!("`{s}`"),
                    Tok::Op(o) => format!("`{o}`"),
                },
                offset: *off,
            },
            None => ExprError::Unexpected {
                src: self.src.to_string(),
                found: "end of condition".into(),
                offset: self.src.chars().count(),
            },
        }
    }
    fn is_word(&self, w: &str) -> bool {
        match self.toks.get(self.pos) {
            Some((Tok::Op(o), _)) => *o == w,
            Some((Tok::Ident(s), _)) => s == w,
            _ => false,
        }
    }
    fn or(&mut self) -> Result<Expr, ExprError> {
        let mut l = self.and()?;
        while self.is_word("or") {
            self.pos += 1;
            let r = self.and()?;
            l = Expr::Or(Box::new(l), Box::new(r));
        }
        Ok(l)
    }
    fn and(&mut self) -> Result<Expr, ExprError> {
        let mut l = self.not()?;
        while self.is_word("and") {
            self.pos += 1;
            let r = self.not()?;
            l = Expr::And(Box::new(l), Box::new(r));
        }
        Ok(l)
    }
    fn not(&mut self) -> Result<Expr, ExprError> {
        if self.is_word("not") {
            self.pos += 1;
            self.depth += 1;
            if self.depth > MAX_DEPTH {
                return Err(self.err());
            }
            let e = self.not()?;
            self.depth -= 1;
            return Ok(Expr::Not(Box::new(e)));
        }
        self.cmp()
    }
    fn cmp(&mut self) -> Result<Expr, ExprError> {
        let l = self.atom()?;
        let op = match self.toks.get(self.pos) {
            Some((Tok::Op("<"), _)) => CmpOp::Lt,
            Some((Tok::Op("<="), _)) => CmpOp::Le,
            Some((Tok::Op(">"), _)) => CmpOp::Gt,
            Some((Tok::Op(">="), _)) => CmpOp::Ge,
            Some((Tok::Op("=="), _)) => CmpOp::Eq,
            Some((Tok::Op("!="), _)) => CmpOp::Ne,
            _ => return Ok(l),
        };
        self.pos += 1;
        let r = self.atom()?;
        Ok(Expr::Cmp(op, Box::new(l), Box::new(r)))
    }
    fn atom(&mut self) -> Result<Expr, ExprError> {
        self.depth += 1;
        if self.depth > MAX_DEPTH {
            return Err(self.err());
        }
        let r = match self.toks.get(self.pos).cloned() {
            Some((Tok::Num(n), _)) => {
                self.pos += 1;
                Ok(Expr::Lit(Value::Number(n)))
            }
            Some((Tok::Ident(s), _)) => match s.as_str() {
                "true" => {
                    self.pos += 1;
                    Ok(Expr::Lit(Value::Bool(true)))
                }
                "false" => {
                    self.pos += 1;
                    Ok(Expr::Lit(Value::Bool(false)))
                }
                "and" | "or" | "not" => Err(self.err()),
                _ => {
                    self.pos += 1;
                    Ok(Expr::Var(s))
                }
            },
            Some((Tok::Op("("), _)) => {
                self.pos += 1;
                let e = self.or()?;
                if !self.is_word(")") {
                    return Err(self.err());
                }
                self.pos += 1;
                Ok(e)
            }
            Some((Tok::Op("-"), _)) => {
                self.pos += 1;
                Ok(Expr::Neg(Box::new(self.atom()?)))
            }
            _ => Err(self.err()),
        };
        self.depth -= 1;
        r
    }
}

impl Expr {
    /// Parses a condition's text.
    ///
    /// # Errors
    /// [`ExprError::Unexpected`] naming the offending token and its character offset.
    pub fn parse(src: &str) -> Result<Expr, ExprError> {
        let toks = tokenize(src)?;
        let mut p = Parser {
            src,
            toks,
            pos: 0,
            depth: 0,
        };
        let e = p.or()?;
        if p.pos != p.toks.len() {
            return Err(p.err());
        }
        Ok(e)
    }

    /// The type of the expression given the types of the variables.
    ///
    /// # Errors
    /// Unknown variables and operators applied to the wrong type.
    pub fn check(&self, ty_of: &dyn Fn(&str) -> Option<ValueType>) -> Result<ValueType, ExprError> {
        let want = |e: &Expr, t: ValueType, op: &'static str| -> Result<(), ExprError> {
            let found = e.check(ty_of)?;
            if found != t {
                return Err(ExprError::TypeMismatch {
                    op,
                    expected: t,
                    found,
                });
            }
            Ok(())
        };
        match self {
            Expr::Lit(v) => Ok(v.ty()),
            Expr::Var(n) => ty_of(n).ok_or_else(|| ExprError::UnknownVariable(n.clone())),
            Expr::Neg(e) => want(e, ValueType::Number, "-").map(|_| ValueType::Number),
            Expr::Not(e) => want(e, ValueType::Bool, "not").map(|_| ValueType::Bool),
            Expr::And(a, b) => {
                want(a, ValueType::Bool, "and")?;
                want(b, ValueType::Bool, "and").map(|_| ValueType::Bool)
            }
            Expr::Or(a, b) => {
                want(a, ValueType::Bool, "or")?;
                want(b, ValueType::Bool, "or").map(|_| ValueType::Bool)
            }
            Expr::Cmp(op, a, b) => {
                let ta = a.check(ty_of)?;
                if matches!(op, CmpOp::Eq | CmpOp::Ne) {
                    want(b, ta, "a comparison").map(|_| ValueType::Bool)
                } else {
                    want(a, ValueType::Number, "an ordering comparison")?;
                    want(b, ValueType::Number, "an ordering comparison").map(|_| ValueType::Bool)
                }
            }
        }
    }

    /// Evaluates the expression. A type-checked expression never meets a mismatch; an unchecked
    /// one treats a missing variable as `false` / `0` and a mismatch as `false` rather than fail.
    pub fn eval(&self, var: &dyn Fn(&str) -> Option<Value>) -> Value {
        let num = |e: &Expr| match e.eval(var) {
            Value::Number(n) => n,
            Value::Bool(b) => f64::from(u8::from(b)),
        };
        let truth = |e: &Expr| matches!(e.eval(var), Value::Bool(true));
        match self {
            Expr::Lit(v) => *v,
            Expr::Var(n) => var(n).unwrap_or(Value::Bool(false)),
            Expr::Neg(e) => Value::Number(-num(e)),
            Expr::Not(e) => Value::Bool(!truth(e)),
            Expr::And(a, b) => Value::Bool(truth(a) && truth(b)),
            Expr::Or(a, b) => Value::Bool(truth(a) || truth(b)),
            Expr::Cmp(op, a, b) => {
                let (x, y) = (num(a), num(b));
                Value::Bool(match op {
                    CmpOp::Lt => x < y,
                    CmpOp::Le => x <= y,
                    CmpOp::Gt => x > y,
                    CmpOp::Ge => x >= y,
                    CmpOp::Eq => x == y,
                    CmpOp::Ne => x != y,
                })
            }
        }
    }

    /// Whether the expression reads variable `name`.
    pub fn mentions(&self, name: &str) -> bool {
        match self {
            Expr::Lit(_) => false,
            Expr::Var(n) => n == name,
            Expr::Neg(e) | Expr::Not(e) => e.mentions(name),
            Expr::And(a, b) | Expr::Or(a, b) | Expr::Cmp(_, a, b) => {
                a.mentions(name) || b.mentions(name)
            }
        }
    }
}

/// A condition as written in the plan, kept with its parsed form. Serialises as its text.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct Condition {
    /// The source text.
    pub src: String,
    /// The parsed expression.
    pub expr: Expr,
}

impl Condition {
    /// Parses a condition.
    ///
    /// # Errors
    /// See [`Expr::parse`].
    pub fn parse(src: &str) -> Result<Self, ExprError> {
        Ok(Self {
            src: src.to_string(),
            expr: Expr::parse(src)?,
        })
    }
    /// Evaluates to a boolean.
    pub fn holds(&self, var: &dyn Fn(&str) -> Option<Value>) -> bool {
        matches!(self.expr.eval(var), Value::Bool(true))
    }
}

impl TryFrom<String> for Condition {
    type Error = ExprError;
    fn try_from(s: String) -> Result<Self, ExprError> {
        Condition::parse(&s)
    }
}

impl From<Condition> for String {
    fn from(c: Condition) -> String {
        c.src
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn vars(n: &str) -> Option<Value> {
        match n {
            "target_found" => Some(Value::Bool(true)),
            "battery_pct" => Some(Value::Number(55.0)),
            _ => None,
        }
    }
    fn types(n: &str) -> Option<ValueType> {
        vars(n).map(|v| v.ty())
    }

    #[test]
    fn evaluates_the_flightplan_example() {
        let e = Expr::parse("target_found and battery_pct > 40").unwrap();
        assert_eq!(e.check(&types), Ok(ValueType::Bool));
        assert_eq!(e.eval(&vars), Value::Bool(true));
        let e = Expr::parse("not (target_found || battery_pct <= -1e1) or false").unwrap();
        assert_eq!(e.eval(&vars), Value::Bool(false));
        assert_eq!(
            Expr::parse("battery_pct = 55").unwrap().eval(&vars),
            Value::Bool(true)
        );
    }

    #[test]
    fn precedence_and_binds_tighter_than_or() {
        let e = Expr::parse("true or false and false").unwrap();
        assert_eq!(e.eval(&vars), Value::Bool(true));
    }

    #[test]
    fn errors_name_the_problem() {
        assert!(matches!(
            Expr::parse("a >"),
            Err(ExprError::Unexpected { .. })
        ));
        assert!(matches!(
            Expr::parse("a # b"),
            Err(ExprError::Unexpected { offset: 2, .. })
        ));
        let e = Expr::parse("nope > 3").unwrap();
        assert_eq!(
            e.check(&types),
            Err(ExprError::UnknownVariable("nope".into()))
        );
        let e = Expr::parse("target_found > 3").unwrap();
        assert!(matches!(
            e.check(&types),
            Err(ExprError::TypeMismatch { .. })
        ));
        let e = Expr::parse("battery_pct and true").unwrap();
        assert!(matches!(
            e.check(&types),
            Err(ExprError::TypeMismatch { .. })
        ));
    }

    #[test]
    fn deep_nesting_is_refused_not_overflowed() {
        let src = "(".repeat(10_000) + "true" + &")".repeat(10_000);
        assert!(Expr::parse(&src).is_err());
        let src = "not ".repeat(10_000) + "true";
        assert!(Expr::parse(&src).is_err());
    }

    proptest! {
        #[test]
        fn parser_never_panics(s in "\\PC{0,40}") {
            if let Ok(e) = Expr::parse(&s) {
                let _ = e.check(&types);
                let _ = e.eval(&vars);
            }
        }
    }
}
