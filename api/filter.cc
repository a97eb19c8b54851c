#include "api/filter.h"

#include <algorithm>
#include <array>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "api/json.h"

namespace oxbow::api {
namespace {

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
    if (!any_of.empty()) {
      bool found = false;
      for (const nlohmann::json& v : any_of) found = found || ScalarEquals(value, v);
      if (!found) return false;
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

class MetadataFilter final : public index::ImageFilter {
 public:
  explicit MetadataFilter(std::vector<Condition> conditions) : conditions_(std::move(conditions)) {}

  bool Matches(const index::ImageRecord& record) const override {
    // Stored by any version: a document too deep to handle safely is not parsed (and cannot match).
    if (record.metadata_json.empty() || JsonNestingDepth(record.metadata_json) > kMaxJsonDepth) return false;
    const auto metadata = nlohmann::json::parse(record.metadata_json, nullptr, /*allow_exceptions=*/false);
    if (!metadata.is_object()) return false;  // also a discarded (invalid) document
    for (const Condition& c : conditions_) {
      const auto it = metadata.find(c.key);
      if (it == metadata.end() || !c.Matches(*it)) return false;
    }
    return true;
  }

 private:
  std::vector<Condition> conditions_;
};

using Failure = std::unexpected<Error>;

Failure Invalid(std::string_view label, const std::string& problem) {
  return Fail(ErrorCode::kInvalidArgument, std::string(label) + ": " + problem);
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
    if (std::find(kOperators.begin(), kOperators.end(), op) == kOperators.end()) {
      return Invalid(label, "unknown operator '" + op + "' for " + where + " (known: in, gt, gte, lt, lte)");
    }
    if (op == "in") {
      if (!operand.is_array() || operand.empty() || operand.size() > kMaxFilterValues) {
        return Invalid(label, "operator 'in' of " + where + " needs an array of 1 to " +
                                  std::to_string(kMaxFilterValues) + " values");
      }
      for (const nlohmann::json& v : operand) {
        if (!IsScalar(v)) {
          return Invalid(label, "operator 'in' of " + where + " takes strings, numbers and booleans, got " +
                                    v.type_name());
        }
        c.any_of.push_back(v);
      }
      continue;
    }
    if (!operand.is_number() && !operand.is_string()) {
      return Invalid(label, "operator '" + op + "' of " + where + " needs a number or a string, got " +
                                operand.type_name());
    }
    if (bound_type != nullptr && bound_type->is_number() != operand.is_number()) {
      return Invalid(label, "the bounds of " + where + " mix numbers and strings");
    }
    bound_type = &operand;
    Bound bound{operand, op.size() == 3};  // gte, lte
    if (op[0] == 'g') {
      c.lower = bound;
    } else {
      c.upper = bound;
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
