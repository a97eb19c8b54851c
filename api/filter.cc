#include "api/filter.h"

#include <algorithm>
#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
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

// Equality of two scalars of the grammar: the same kind (number, string, boolean) and value.
bool ScalarEquals(const nlohmann::json& a, const nlohmann::json& b) {
  if (a.is_number() && b.is_number()) return a.get<double>() == b.get<double>();
  if (a.is_string() && b.is_string()) return a.get_ref<const std::string&>() == b.get_ref<const std::string&>();
  if (a.is_boolean() && b.is_boolean()) return a.get<bool>() == b.get<bool>();
  return false;
}

// -1, 0 or 1 for value vs bound, nullopt when they are not both numbers or both strings.
std::optional<int> Compare(const nlohmann::json& value, const nlohmann::json& bound) {
  if (value.is_number() && bound.is_number()) {
    const double v = value.get<double>();
    const double b = bound.get<double>();
    return v < b ? -1 : (v > b ? 1 : 0);
  }
  if (value.is_string() && bound.is_string()) {
    const int c = value.get_ref<const std::string&>().compare(bound.get_ref<const std::string&>());
    return c < 0 ? -1 : (c > 0 ? 1 : 0);
  }
  return std::nullopt;
}

struct Bound {
  nlohmann::json value;
  bool inclusive = false;
};

// One key of the filter: equal to one of `any_of` (when not empty) and within the bounds.
struct Condition {
  std::string key;
  std::vector<nlohmann::json> any_of;
  std::optional<Bound> lower, upper;

  bool Matches(const nlohmann::json& value) const {
    if (!any_of.empty() &&
        std::none_of(any_of.begin(), any_of.end(), [&](const nlohmann::json& v) { return ScalarEquals(value, v); })) {
      return false;
    }
    if (lower) {
      const auto c = Compare(value, lower->value);
      if (!c || *c < 0 || (*c == 0 && !lower->inclusive)) return false;
    }
    if (upper) {
      const auto c = Compare(value, upper->value);
      if (!c || *c > 0 || (*c == 0 && !upper->inclusive)) return false;
    }
    return true;
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
  bool null() override { return Ignored() || Value(nlohmann::json()); }
  bool boolean(bool v) override { return Ignored() || Value(v); }
  bool number_integer(number_integer_t v) override { return Ignored() || Value(v); }
  bool number_unsigned(number_unsigned_t v) override { return Ignored() || Value(v); }
  bool number_float(number_float_t v, const string_t& /*text*/) override { return Ignored() || Value(v); }
  bool string(string_t& v) override { return Ignored() || Value(v); }
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
  // A top-level member's value a condition names, or the root itself (depth 0: not an object, no match).
  bool Value(const nlohmann::json& v) {
    if (depth_ == 0 || !conditions_[current_].Matches(v)) return false;
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

// The texts one of which a document whose every string is written without escapes must contain when
// the condition can hold: "\"v\"" for a string v, "true"/"false" for a boolean. Empty (no quick test)
// when a number is among the values (2004 can be written 2004.0 or 2.004e3), for a string that would
// need escaping, or for a condition of bounds only.
std::vector<std::string> Needles(const Condition& c) {
  std::vector<std::string> needles;
  for (const nlohmann::json& v : c.any_of) {
    if (v.is_boolean()) {
      needles.emplace_back(v.get<bool>() ? "true" : "false");
      continue;
    }
    if (!v.is_string()) return {};
    const auto& text = v.get_ref<const std::string&>();
    const auto needs_escape = [](char ch) { return ch == '"' || ch == '\\' || static_cast<unsigned char>(ch) < 0x20; };
    if (std::any_of(text.begin(), text.end(), needs_escape)) return {};
    needles.push_back('"' + text + '"');
  }
  return needles;
}

class MetadataFilter final : public index::ImageFilter {
 public:
  explicit MetadataFilter(std::vector<Condition> conditions) : conditions_(std::move(conditions)) {
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

 private:
  std::vector<Condition> conditions_;
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
      c->any_of.push_back(v);
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
  const Bound bound{operand, op.size() == 3};  // gte, lte
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
    c.any_of.push_back(spec);
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
  return std::make_shared<const MetadataFilter>(std::move(conditions));
}

}  // namespace oxbow::api
