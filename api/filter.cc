#include "api/filter.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <optional>
#include <string>
#include <string_view>
#include <type_traits>
#include <unordered_set>
#include <utility>
#include <variant>
#include <vector>

#include <nlohmann/json.hpp>

#include "api/json.h"

namespace oxbow::api {
namespace {

static_assert(kMaxFilterKeys <= 64, "Matcher keeps one bit per condition");

// The grammar's deepest nesting: filter object > operator object > "in" array.
constexpr int kMaxFilterDepth = 3;

constexpr std::array<std::string_view, 5> kOperators = {"in", "gt", "gte", "lt", "lte"};

bool IsScalar(const nlohmann::json& v) { return v.is_string() || v.is_number() || v.is_boolean(); }

// A JSON number as the value it denotes, in one representation per value so that equal values are equal
// alternatives (a hash set finds them): an integral value in [-2^63, 2^64) as int64_t, or as uint64_t
// above INT64_MAX; any other value (a fraction, or beyond that range) as double. A number written with
// a fraction or an exponent is the double nearest to it (9007199254740993.0 is 2^53).
using Number = std::variant<int64_t, uint64_t, double>;

Number FromUnsigned(uint64_t v) {
  return v <= static_cast<uint64_t>(std::numeric_limits<int64_t>::max()) ? Number(static_cast<int64_t>(v)) : Number(v);
}

Number FromDouble(double v) {
  if (std::trunc(v) == v) {
    if (v >= -0x1p63 && v < 0x1p63) return static_cast<int64_t>(v);
    if (v >= 0x1p63 && v < 0x1p64) return static_cast<uint64_t>(v);
  }
  return v;
}

// The number of a JSON value that is a number.
Number NumberOf(const nlohmann::json& v) {
  if (v.is_number_unsigned()) return FromUnsigned(v.get<uint64_t>());
  if (v.is_number_integer()) return v.get<int64_t>();
  return FromDouble(v.get<double>());
}

template <typename T>
int Sign(T a, T b) {
  return a < b ? -1 : (a > b ? 1 : 0);
}

// -1, 0 or 1 for the integer i vs the double d, exactly (no rounding of i to a double).
template <typename Int>
int CompareIntegerToDouble(Int i, double d) {
  constexpr double kLow = std::is_signed_v<Int> ? -0x1p63 : 0.0;  // the integer type's range, as doubles
  constexpr double kHigh = std::is_signed_v<Int> ? 0x1p63 : 0x1p64;
  if (d >= kHigh) return -1;
  if (d < kLow) return 1;
  const double whole = std::trunc(d);  // in [kLow, kHigh): converts exactly
  const auto whole_int = static_cast<Int>(whole);
  if (i != whole_int) return Sign(i, whole_int);
  return Sign(whole, d);  // i == whole: d's fraction decides
}

// -1, 0 or 1 for a vs b, exactly, whatever their representations.
int Compare(const Number& a, const Number& b) {
  return std::visit(
      [](auto x, auto y) -> int {
        using X = decltype(x);
        using Y = decltype(y);
        if constexpr (std::is_same_v<X, Y>) {
          return Sign(x, y);
        } else if constexpr (std::is_same_v<X, double>) {
          return -CompareIntegerToDouble(y, x);
        } else if constexpr (std::is_same_v<Y, double>) {
          return CompareIntegerToDouble(x, y);
        } else if constexpr (std::is_same_v<X, int64_t>) {  // y is uint64_t
          return x < 0 ? -1 : Sign(static_cast<uint64_t>(x), y);
        } else {  // x is uint64_t, y int64_t
          return y < 0 ? 1 : Sign(x, static_cast<uint64_t>(y));
        }
      },
      a, b);
}

int Compare(std::string_view a, std::string_view b) {
  const int c = a.compare(b);
  return c < 0 ? -1 : (c > 0 ? 1 : 0);
}

// A bound of a range: a number or a string (ParseOperator keeps one key's bounds of one kind).
struct Bound {
  std::variant<Number, std::string> value;
  bool inclusive = false;
};

// True when `c`, the comparison of a value with a lower (`lower`) or upper bound, keeps the value in range.
bool Within(int c, bool lower, bool inclusive) { return (lower ? c > 0 : c < 0) || (c == 0 && inclusive); }

// One key of the filter: equal to one of the "in" values (when there are some) and within the bounds.
// The values are hash sets built once per filter, so a document costs the same whatever their number.
struct Condition {
  std::string key;
  bool has_values = false;  // an equality or "in": the member must equal one of the values below
  std::unordered_set<std::string> strings;
  std::unordered_set<Number> numbers;
  bool any_true = false, any_false = false;
  std::optional<Bound> lower, upper;

  bool MatchesString(const std::string& v) const {
    if (has_values && !strings.contains(v)) return false;
    const auto within = [&](const std::optional<Bound>& b, bool is_lower) {
      const auto* text = b ? std::get_if<std::string>(&b->value) : nullptr;
      return !b || (text != nullptr && Within(Compare(v, *text), is_lower, b->inclusive));
    };
    return within(lower, true) && within(upper, false);
  }
  bool MatchesNumber(const Number& v) const {
    if (has_values && !numbers.contains(v)) return false;
    const auto within = [&](const std::optional<Bound>& b, bool is_lower) {
      const auto* number = b ? std::get_if<Number>(&b->value) : nullptr;
      return !b || (number != nullptr && Within(Compare(v, *number), is_lower, b->inclusive));
    };
    return within(lower, true) && within(upper, false);
  }
  // Bounds are numbers or strings: a boolean never lies within one.
  bool MatchesBoolean(bool v) const { return has_values && (v ? any_true : any_false) && !lower && !upper; }

  // Adds a scalar of the grammar to the values.
  void AddValue(const nlohmann::json& v) {
    has_values = true;
    if (v.is_string()) {
      strings.insert(v.get<std::string>());
    } else if (v.is_boolean()) {
      (v.get<bool>() ? any_true : any_false) = true;
    } else {
      numbers.insert(NumberOf(v));
    }
  }
};

// Reads a metadata document as events (nlohmann's SAX interface: no document tree is built, and the
// parser keeps its own stack, so any nesting is safe) and checks each top-level member a condition
// names as it goes by, stopping at the first that fails (server/README.md, Filtered search).
class Matcher final : public nlohmann::json_sax<nlohmann::json> {
 public:
  explicit Matcher(const std::vector<Condition>& conditions)
      : conditions_(conditions), all_(conditions.size() == 64 ? ~uint64_t{0} : (uint64_t{1} << conditions.size()) - 1) {}

  // True when the document is an object and every condition held (parsed to the end: an invalid
  // document matches nothing).
  bool Run(const std::string& text) {
    return nlohmann::json::sax_parse(text, this) && root_is_object_ && seen_ == all_;
  }

  // A value no condition looks at is not converted (a string would be copied).
  bool null() override {
    return Ignored() || Value([](const Condition& /*c*/) { return false; });  // every condition needs a value
  }
  bool boolean(bool v) override {
    return Ignored() || Value([&](const Condition& c) { return c.MatchesBoolean(v); });
  }
  bool number_integer(number_integer_t v) override {
    return Ignored() || Value([&](const Condition& c) { return c.MatchesNumber(Number(int64_t{v})); });
  }
  bool number_unsigned(number_unsigned_t v) override {
    return Ignored() || Value([&](const Condition& c) { return c.MatchesNumber(FromUnsigned(v)); });
  }
  bool number_float(number_float_t v, const string_t& /*text*/) override {
    return Ignored() || Value([&](const Condition& c) { return c.MatchesNumber(FromDouble(v)); });
  }
  bool string(string_t& v) override {
    return Ignored() || Value([&](const Condition& c) { return c.MatchesString(v); });
  }
  bool binary(binary_t& /*v*/) override { return false; }  // not produced by the JSON text format
  bool start_object(std::size_t /*elements*/) override {
    if (depth_ == 0) root_is_object_ = true;
    return Container();
  }
  bool end_object() override {
    --depth_;
    return true;
  }
  bool start_array(std::size_t /*elements*/) override { return Container(); }
  bool end_array() override {
    --depth_;
    return true;
  }
  bool key(string_t& k) override {
    if (depth_ == 1) {
      current_ = kNone;
      for (size_t i = 0; i < conditions_.size(); ++i) {
        if (conditions_[i].key == k) current_ = i;
      }
    }
    return true;
  }
  bool parse_error(std::size_t /*position*/, const std::string& /*last_token*/,
                   const nlohmann::detail::exception& /*ex*/) override {
    return false;
  }

 private:
  static constexpr size_t kNone = static_cast<size_t>(-1);

  // Inside a member's object or array, or in a member no condition names.
  bool Ignored() const { return depth_ > 1 || (depth_ == 1 && current_ == kNone); }
  // A top-level member's value a condition names (`holds` tells whether the condition holds for it),
  // or the root itself (depth 0: not an object, no match).
  template <typename Holds>
  bool Value(const Holds& holds) {
    if (depth_ == 0 || !holds(conditions_[current_])) return false;
    seen_ |= uint64_t{1} << current_;
    current_ = kNone;
    return true;
  }
  // An object or array: a condition's member holding one does not match.
  bool Container() {
    if (depth_ == 1 && current_ != kNone) return false;
    ++depth_;
    return true;
  }

  const std::vector<Condition>& conditions_;
  const uint64_t all_;      // a bit per condition
  uint64_t seen_ = 0;       // the conditions whose member was seen and matched
  size_t current_ = kNone;  // the condition of the top-level member being read
  int depth_ = 0;
  bool root_is_object_ = false;
};

// Needles a quick test looks for at most per condition: each is one search of the document's text,
// and past a few of them the parse (which looks each value up in a hash set) costs less.
constexpr size_t kMaxNeedles = 8;

// The texts one of which a document whose every string is written without escapes must contain when
// the condition can hold: "\"v\"" for a string v, "true"/"false" for a boolean. Empty (no quick test)
// when a number is among the values (2004 can be written 2004.0 or 2.004e3), for a string that would
// need escaping, for more than kMaxNeedles values, or for a condition of bounds only.
std::vector<std::string> Needles(const Condition& c) {
  if (!c.numbers.empty() || c.strings.size() + (c.any_true ? 1 : 0) + (c.any_false ? 1 : 0) > kMaxNeedles) return {};
  std::vector<std::string> needles;
  if (c.any_true) needles.emplace_back("true");
  if (c.any_false) needles.emplace_back("false");
  const auto needs_escape = [](char ch) { return ch == '"' || ch == '\\' || static_cast<unsigned char>(ch) < 0x20; };
  for (const std::string& text : c.strings) {
    if (std::any_of(text.begin(), text.end(), needs_escape)) return {};
    needles.push_back('"' + text + '"');
  }
  return needles;
}

class MetadataFilter final : public index::ImageFilter {
 public:
  MetadataFilter(std::vector<Condition> conditions, std::string text)
      : conditions_(std::move(conditions)), text_(std::move(text)) {
    for (const Condition& c : conditions_) needles_.push_back(Needles(c));
  }

  bool Matches(const index::ImageRecord& record) const override {
    const std::string_view text = record.metadata_json;
    if (text.empty()) return false;
    // Quick rejection before parsing (a selective filter rejects most images): in a text without a
    // backslash every string is written as its bytes, so a member equal to one of a condition's
    // values puts one of its needles in the text.
    if (text.find('\\') == std::string_view::npos) {
      for (const std::vector<std::string>& needles : needles_) {
        if (!needles.empty() && std::none_of(needles.begin(), needles.end(), [&](const std::string& n) {
              return text.find(n) != std::string_view::npos;
            })) {
          return false;
        }
      }
    }
    return Matcher(conditions_).Run(record.metadata_json);
  }

  std::string Text() const override { return text_; }

 private:
  std::vector<Condition> conditions_;
  std::string text_;  // what it was parsed from
  std::vector<std::vector<std::string>> needles_;  // per condition (Needles)
};

using Failure = std::unexpected<Error>;

Failure Invalid(std::string_view label, const std::string& problem) {
  return Fail(ErrorCode::kInvalidArgument, std::string(label) + ": " + problem);
}

// One operator of a condition's object into `c`; `bound_type`: the first bound seen (null: none yet).
Status ParseOperator(std::string_view label, const std::string& where, const std::string& op,
                     const nlohmann::json& operand, Condition* c, const nlohmann::json** bound_type) {
  if (std::find(kOperators.begin(), kOperators.end(), op) == kOperators.end()) {
    return Invalid(label, "unknown operator '" + op + "' for " + where + " (known: in, gt, gte, lt, lte)");
  }
  const std::string named = "operator '" + op + "' of " + where;
  if (op == "in") {
    if (!operand.is_array() || operand.empty() || operand.size() > kMaxFilterValues) {
      return Invalid(label, named + " needs an array of 1 to " + std::to_string(kMaxFilterValues) + " values");
    }
    for (const nlohmann::json& v : operand) {
      if (!IsScalar(v)) return Invalid(label, named + " takes strings, numbers and booleans, got " + v.type_name());
      c->AddValue(v);
    }
    return Ok();
  }
  if (!operand.is_number() && !operand.is_string()) {
    return Invalid(label, named + " needs a number or a string, got " + operand.type_name());
  }
  if (*bound_type != nullptr && (*bound_type)->is_number() != operand.is_number()) {
    return Invalid(label, "the bounds of " + where + " mix numbers and strings");
  }
  *bound_type = &operand;
  Bound bound;
  bound.inclusive = op.size() == 3;  // gte, lte
  if (operand.is_number()) {
    bound.value = NumberOf(operand);
  } else {
    bound.value = operand.get<std::string>();
  }
  if (op[0] == 'g') {
    c->lower = bound;
  } else {
    c->upper = bound;
  }
  return Ok();
}

Result<Condition> ParseCondition(std::string_view label, const std::string& key, const nlohmann::json& spec) {
  Condition c;
  c.key = key;
  const std::string where = "key '" + key + "'";
  if (IsScalar(spec)) {
    c.AddValue(spec);
    return c;
  }
  if (!spec.is_object()) {
    return Invalid(label, where + " must be a string, number, boolean or an object of operators (in, gt, gte, lt, "
                                  "lte), got " + spec.type_name());
  }
  if (spec.empty()) return Invalid(label, where + ": an operator object needs at least one of in, gt, gte, lt, lte");
  const nlohmann::json* bound_type = nullptr;
  for (const auto& [op, operand] : spec.items()) {
    if (auto parsed = ParseOperator(label, where, op, operand, &c, &bound_type); !parsed) {
      return std::unexpected(parsed.error());
    }
  }
  return c;
}

}  // namespace

Result<std::shared_ptr<const index::ImageFilter>> ParseFilter(std::string_view text, std::string_view label) {
  // Both limits before parsing (ParseMetadata's reasons).
  if (text.size() > kMaxFilterBytes) {
    return Invalid(label, "must be at most " + std::to_string(kMaxFilterBytes) + " bytes, got " +
                              std::to_string(text.size()));
  }
  if (JsonNestingDepth(text, kMaxFilterDepth) > kMaxFilterDepth) {
    return Invalid(label, "nests deeper than " + std::to_string(kMaxFilterDepth) +
                              " levels (filter object, operator object, 'in' array)");
  }
  const auto json = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (json.is_discarded()) return Invalid(label, "is not valid JSON");
  if (!json.is_object()) {
    return Invalid(label, std::string("must be a JSON object of metadata keys, got ") + json.type_name());
  }
  if (json.size() > kMaxFilterKeys) {
    return Invalid(label, "has " + std::to_string(json.size()) + " keys, at most " + std::to_string(kMaxFilterKeys) +
                              " allowed");
  }
  if (json.empty()) return std::shared_ptr<const index::ImageFilter>();
  std::vector<Condition> conditions;
  for (const auto& [key, spec] : json.items()) {
    auto condition = ParseCondition(label, key, spec);
    if (!condition) return std::unexpected(condition.error());
    conditions.push_back(std::move(*condition));
  }
  return std::make_shared<const MetadataFilter>(std::move(conditions), std::string(text));
}

}  // namespace oxbow::api
